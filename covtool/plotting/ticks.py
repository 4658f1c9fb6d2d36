"""Tick labels drawn as plain text: log-axis labels without mathtext.

Matplotlib's :class:`~matplotlib.ticker.LogFormatterSciNotation` writes each
log-axis label as mathtext (``$\\mathdefault{10^{-2}}$``), and every process
that draws a figure parses each distinct label again with pyparsing (about
30 ms each on the 2-core machine: a quarter to a third of the time to draw a
figure with a log axis).  :class:`PlainLogFormatter` gives the same labels,
on the same ticks, as plain Unicode text (``10⁻²``, ``2×10³``), which the
font renders directly.
"""

from __future__ import annotations

import re

import matplotlib as mpl
from matplotlib.ticker import LogFormatterSciNotation

#: superscript digits and minus (DejaVu Sans, matplotlib's default font, has every one)
_SUPERSCRIPT = str.maketrans("-0123456789", "\u207b\u2070\u00b9\u00b2\u00b3\u2074\u2075\u2076\u2077\u2078\u2079")
#: the mathtext forms LogFormatterSciNotation writes: $\mathdefault{…}$ around 10^{e}, c\times10^{e} or %g
_MATHDEFAULT = re.compile(r"^\$\\mathdefault\{(.*)\}\$$")
_POWER = re.compile(r"\^\{(-?\d+)\}")


def plain_label(label: str) -> str:
    """``label`` of :class:`~matplotlib.ticker.LogFormatterSciNotation` as plain text.

    ``$\\mathdefault{10^{-2}}$`` → ``10⁻²``, ``$\\mathdefault{2\\times10^{3}}$``
    → ``2×10³``, ``$\\mathdefault{-5}$`` → ``−5`` (with ``axes.unicode_minus``);
    any other label (empty, or not of these forms) is returned unchanged.
    """
    m = _MATHDEFAULT.match(label)
    if m is None:
        return label
    body = _POWER.sub(lambda e: e.group(1).translate(_SUPERSCRIPT), m.group(1).replace("\\times", "\u00d7"))
    if "\\" in body or "{" in body:                 # not a form this knows: left to mathtext
        return label
    return "\u2212" + body[1:] if body.startswith("-") and mpl.rcParams["axes.unicode_minus"] else body


class PlainLogFormatter(LogFormatterSciNotation):
    """:class:`~matplotlib.ticker.LogFormatterSciNotation` whose labels are plain text (:func:`plain_label`).

    The same ticks are labelled (``labelOnlyBase``, the minor-tick
    thresholds); under ``text.usetex`` the labels are left to TeX.
    """

    def __call__(self, x, pos=None):
        label = super().__call__(x, pos)
        return label if mpl.rcParams["text.usetex"] else plain_label(label)


__all__ = ["PlainLogFormatter", "plain_label"]

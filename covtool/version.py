"""covtool's version (one home: pyproject.toml reads it too)."""

__version__ = "0.1.0"


def source_revision() -> str:
    """The covtool source a result came from, for provenance.

    Returns
    -------
    str
        ``git rev-parse HEAD`` of the repository the imported package lies
        in (with ``" (modified)"`` when tracked files differ from that
        commit), else ``"<version> (not a git checkout)"`` for an installed
        package or when git is not available.
    """
    global _REVISION
    if _REVISION is None:
        _REVISION = _git_revision() or f"{__version__} (not a git checkout)"
    return _REVISION


_REVISION = None


def _git_revision():
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():          # a directory, or a file in a git worktree
        return None
    try:
        def git(*args):
            return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
        head = git("rev-parse", "HEAD")
        if head.returncode != 0:
            return None
        dirty = git("diff", "--quiet", "HEAD", "--", "covtool", "models").returncode == 1
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + (" (modified)" if dirty else "")

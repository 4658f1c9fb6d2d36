"""Figures of the studies (matplotlib, imported only when a figure is drawn).

One module per study kind whose figure-drawing code could be moved out of
its runner unchanged; the other runners still build their figures
themselves (a later step draws every figure from the result objects here).
"""

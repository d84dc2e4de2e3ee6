"""Experiments and presentation on top of the codec: the paper's sweep (Fig. 5) and
comparison (Fig. 6), file evaluation, figures, the demo and a synthetic terrain.

Nothing in the codec stages imports from here.
"""

"""Tools that ``make`` runs beside the product: the quality protocol (``quality``, with its
baselines and style floor), the structure reference (``structure``), the documents' figures
(``*_figure``) and the pack for training on a lent GPU (``gpu_pack``).

Not part of the installed package: run from the repository root (``make quality``).
"""

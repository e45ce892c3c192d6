"""Readers of published hand datasets, one module per dataset; each writes a torchhand
sequence folder (datasets/README.md) from one of the dataset's sequences, as published.

``FORMATS`` names them for ``torchhand import --format NAME SRC --out SEQ``; every reader
is called as ``reader(src, out, force=False, segmentation=None)`` and returns the written
:class:`~torchhand.data.layout.SequenceInfo`.
"""

from __future__ import annotations

from torchhand.data.datasets.fpha import import_fpha

__all__ = ["FORMATS", "import_fpha"]

#: ``--format`` name -> reader: First-Person Hand Action (Garcia-Hernando et al., CVPR 2018).
FORMATS = {"fpha": import_fpha}

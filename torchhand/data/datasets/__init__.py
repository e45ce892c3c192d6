"""Readers of published hand datasets, one module per dataset; each writes a torchhand
sequence folder (datasets/README.md) from one of the dataset's sequences, as published.

``FORMATS`` names them for ``torchhand import --format NAME SRC --out SEQ``; every reader
is called as ``reader(src, out, force=False, segmentation=None, **options)`` (``options``:
the dataset's own, e.g. NYU's ``camera``, DexYCB's ``cameras``) and returns the written
:class:`~torchhand.data.layout.SequenceInfo`.
"""

from __future__ import annotations

from torchhand.data.datasets.dexycb import import_dexycb
from torchhand.data.datasets.fpha import import_fpha
from torchhand.data.datasets.ho3d import import_ho3d
from torchhand.data.datasets.nyu import import_nyu

__all__ = ["FORMATS", "import_dexycb", "import_fpha", "import_ho3d", "import_nyu"]

#: ``--format`` name -> reader: First-Person Hand Action (Garcia-Hernando et al., CVPR 2018);
#: the NYU hand pose dataset (Tompson et al., 2014); HO-3D (Hampali et al., CVPR 2020);
#: DexYCB (Chao et al., CVPR 2021).
FORMATS = {"fpha": import_fpha, "nyu": import_nyu, "ho3d": import_ho3d, "dexycb": import_dexycb}

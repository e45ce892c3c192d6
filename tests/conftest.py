"""Shared fixtures of the torchhand tests.

* ``hia_root``: the thesis data (``shared/data/hands_in_action`` beside the repo);
  tests that need it are skipped when it is absent.
* ``device`` / ``dtype``: parametrisation in the kornia style. A test that takes
  ``device`` runs on the CPU and, when available, on CUDA; a test that takes ``dtype``
  runs in float32 and float64. An explicit ``@pytest.mark.parametrize("dtype", ...)``
  in a test overrides these fixtures.
* ``tmp_thesis_model``: a tiny, valid thesis model (a 3-bone chain) written to
  ``tmp_path``, so that bad-input tests can corrupt copies of its files.
* ``model64``: a session cache of the shipped models in float64 (do not mutate them).
* ``scene_at``: ``scene_at(names, centres)`` -> (float64 Scene, (1, D) theta) with each
  model's rest shape moved so that its centroid lies at its centre (mm, camera frame).

Tiers: tests marked ``@pytest.mark.slow`` (end-to-end and benchmark-like runs) are
skipped unless ``--runslow`` is given; ``python -m pytest -q --runslow -m slow`` runs
only them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List

import numpy as np
import pytest
import torch

# torch warns once that sparse CSR support is in beta (the sparse skinning-matrix tests).
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run the tests marked slow (end-to-end and benchmark-like runs)")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` are skipped unless ``--runslow`` is given."""
    if config.getoption("--runslow"):
        return
    skip_slow = pytest.mark.skip(reason="slow: run with --runslow")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip_slow)


def pytest_configure(config):
    config.addinivalue_line("filterwarnings", "ignore:Sparse CSR tensor support is in beta state:UserWarning")
    # torch.autograd.functional.jacobian(vectorize=True) scripts helpers internally
    config.addinivalue_line("filterwarnings", "ignore:`torch.jit.script` is deprecated:DeprecationWarning")

HIA_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "hands_in_action"
SHIPPED_MODELS = ("hand_right", "hand_left", "ball", "cube", "pipe", "rope")


@pytest.fixture(scope="session")
def scene_at():
    from torchhand.model.scene import Scene

    def make(names, centres):
        scene = Scene.from_names(list(names), dtype=torch.float64)
        theta = torch.zeros(1, scene.num_dofs, dtype=torch.float64)
        for name, model, centre in zip(scene.names, scene.models, centres):
            s = scene.slices[name]
            theta[0, s.start:s.start + 3] = torch.tensor(centre, dtype=torch.float64) - model.vertices_rest.mean(0)
        return scene, theta

    return make


# ------------------------------------------------------------------ data root
@pytest.fixture(scope="session")
def hia_root() -> Path:
    """Root of the thesis' Hands-in-Action data; skips the test when it is absent."""
    if not (HIA_ROOT / "Models").is_dir() or not (HIA_ROOT / "Configs").is_dir():
        pytest.skip(f"thesis data not found at {HIA_ROOT}")
    return HIA_ROOT


# --------------------------------------------------------- device / dtype (kornia style)
def get_test_devices() -> Dict[str, torch.device]:
    """cpu, plus cuda when a CUDA device is available."""
    devices = {"cpu": torch.device("cpu")}
    if torch.cuda.is_available():
        devices["cuda"] = torch.device("cuda:0")
    return devices


def get_test_dtypes() -> Dict[str, torch.dtype]:
    return {"float32": torch.float32, "float64": torch.float64}


TEST_DEVICES = get_test_devices()
TEST_DTYPES = get_test_dtypes()


@pytest.fixture(params=list(TEST_DEVICES.values()), ids=list(TEST_DEVICES))
def device(request) -> torch.device:
    return request.param


@pytest.fixture(params=list(TEST_DTYPES.values()), ids=list(TEST_DTYPES))
def dtype(request) -> torch.dtype:
    return request.param


def tolerance(dtype: torch.dtype) -> Dict[str, float]:
    """``assert_close`` tolerances for values of order 1 in the given dtype."""
    if dtype == torch.float64:
        return dict(rtol=1e-10, atol=1e-10)
    return dict(rtol=1e-5, atol=1e-5)


requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


# ------------------------------------------------------------- shipped models
@pytest.fixture(scope="session")
def model64():
    """``model64(name)``: a cached float64 shipped model. Treat it as read-only."""
    from torchhand import load_model

    cache = {}

    def get(name: str):
        if name not in cache:
            cache[name] = load_model(name, dtype=torch.float64)
        return cache[name]

    return get


def random_theta(model, batch: int, generator: torch.Generator, root_translation: float = 100.0,
                 root_rotation: float = 1.0, margin: float = 0.0) -> torch.Tensor:
    """Random poses inside the joint limits (shrunk by ``margin`` rad), with a random
    root translation in [-root_translation, root_translation] mm and rotation vector
    components in [-root_rotation, root_rotation] rad. dtype/device of the model."""
    lo, hi = model.lower.clone(), model.upper.clone()
    lo[:3], hi[:3] = -root_translation, root_translation
    lo[3:6], hi[3:6] = -root_rotation, root_rotation
    lo[6:], hi[6:] = lo[6:] + margin, hi[6:] - margin
    u = torch.rand(batch, model.num_dofs, generator=generator, dtype=torch.float64)
    return (lo.double().cpu() + (hi - lo).double().cpu() * u).to(lo)


def orthonormalised(R: np.ndarray) -> np.ndarray:
    """Nearest rotation matrices (polar decomposition) of (..., 3, 3) arrays."""
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


@pytest.fixture(scope="session")
def rigid_model64(model64):
    """``rigid_model64(name)``: a float64 shipped model whose rest transforms are
    re-orthonormalised (the thesis stores rotations with 6 digits)."""
    import dataclasses

    from torchhand.model.articulated import ArticulatedModel

    cache = {}

    def get(name: str):
        if name not in cache:
            a = model64(name).assets
            rest = a.rest_transforms.copy()
            rest[:, :3, :3] = orthonormalised(rest[:, :3, :3])
            cache[name] = ArticulatedModel(dataclasses.replace(a, rest_transforms=rest), dtype=torch.float64)
        return cache[name]

    return get


# ----------------------------------------------------------- tiny thesis model
@dataclass
class TinyThesisModel:
    """A tiny valid thesis model on disk, and the values its files hold."""

    dir: Path
    name: str
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    bone_names: List[str]
    weights: np.ndarray  # (V, J) as written (4 decimals, rows sum to 1)
    lengths: List[float]
    motion: Dict[str, np.ndarray]  # bone -> (N, 4, 4)
    num_motion_rows: int
    num_revolute: int
    lines: Dict[str, List[str]] = field(default_factory=dict)  # extension -> file lines

    def path(self, ext: str) -> Path:
        return self.dir / f"{self.name}.{ext}"

    def rewrite(self, ext: str, lines: List[str]) -> Path:
        """Replace the content of one file with ``lines``; returns its path."""
        p = self.path(ext)
        p.write_text("\n".join(lines) + "\n")
        return p


def _rot_z(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _write_tiny_model(d: Path, name: str = "Model_Object_Chain") -> TinyThesisModel:
    d.mkdir(parents=True, exist_ok=True)
    bones = ["Root", "B1", "B2"]
    lengths = [30.0, 20.0, 10.0]
    origins = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    # A strip of 2 x 7 vertices along x, 12 triangles.
    xs = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    vertices = np.array([[x, y, 0.0] for x in xs for y in (-3.0, 3.0)])
    faces = []
    for k in range(len(xs) - 1):
        a, b, c, e = 2 * k, 2 * k + 1, 2 * k + 2, 2 * k + 3
        faces += [[a, c, b], [b, c, e]]
    faces = np.array(faces, dtype=np.int64)
    # Weights: rigid near bone middles, blended at the joints; 4 decimals, rows sum to 1.
    per_x = {0.0: (1, 0, 0), 10.0: (1, 0, 0), 20.0: (0.75, 0.25, 0), 30.0: (0.5, 0.5, 0),
             40.0: (0.1, 0.8, 0.1), 50.0: (0, 0.5, 0.5), 60.0: (0, 0, 1)}
    weights = np.array([per_x[x] for x in xs for _ in (0, 1)], dtype=np.float64)

    off = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    off += [" ".join(f"{c:g}" for c in v) for v in vertices]
    off += [f"3 {a} {b} {c}" for a, b, c in faces]

    N = 3
    skel = [str(N), "Root_NULL_Bone_0", "Root", "30", "Root", "B1", "20", "B1", "B2", "10"]
    skin = ["3", "Root B1 B2 "] + [" ".join(f"{w:.4f}" for w in row) + " " for row in weights]

    big = "-3.40282e+38 3.40282e+38"
    limits = ["Root", "1 1 1 1", "1 0 0", "0 1 0", "0 0 1", big, big, big, "",
              "B1", "0 0 1 1", "1 0 0", "0 1 0", "0 0 1", "-10 10", "-45 30", "-60 90", "",
              "B2", "0 0 0 1", "1 0 0", "0 1 0", "0 0 1", "0 0", "0 0", "-90 45"]
    zones = ["2", "Root", "B", "0.5", "1.0"]

    # MOTION: row 0 is the rest pose; rows 1.. rotate the chain about z and translate it.
    motion = {}
    for j, b in enumerate(bones):
        rows = []
        for n in range(N):
            M = np.eye(4)
            M[:3, :3] = _rot_z(10.0 * n)
            M[:3, 3] = _rot_z(10.0 * n) @ origins[j] + np.array([1.0, 2.0, 3.0]) * n
            rows.append(M)
        motion[b] = np.stack(rows)
    mot = []
    for b in bones:
        mot.append(b)
        for M in motion[b]:
            mot.append(" ".join(f"{x:.9g}" for x in list(M[:3, :3].reshape(-1)) + list(M[:3, 3])) + " ")

    files = {"OFF": off, "SKEL": skel, "SKIN": skin, "LIMITS": limits, "ZONES": zones, "MOTION": mot}
    for ext, lines in files.items():
        (d / f"{name}.{ext}").write_text("\n".join(lines) + "\n")
    return TinyThesisModel(d, name, vertices, faces, bones, weights, lengths, motion, N,
                           num_revolute=3, lines=files)


@pytest.fixture
def tmp_thesis_model(tmp_path) -> TinyThesisModel:
    """A tiny valid thesis model (3-bone chain Root-B1-B2, 14 vertices, 12 triangles,
    9 DoF) with OFF/SKEL/SKIN/LIMITS/ZONES/MOTION files in ``tmp_path / "Models"``."""
    return _write_tiny_model(tmp_path / "Models")


@pytest.fixture(scope="session")
def real_right_hand(hia_root):
    """Parsed thesis files of ``Models/01/Model_Hand_R`` (read once per session)."""
    from torchhand.io import read_thesis_model

    return read_thesis_model(hia_root / "Models" / "01", "Model_Hand_R")

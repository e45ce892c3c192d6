"""Energy terms of the tracking objective (thesis Eq. 4.5), one module per term, one
interface (:mod:`torchhand.tracking.energies.base`), weights and robust losses as
wrappers (:mod:`torchhand.tracking.energies.wrappers`).

``parse_energy("LO+C")`` builds the terms named on the command line with the tracker's
weights and losses: ``LO`` is model-to-data plus data-to-model (depth), ``C`` adds collisions,
``S`` salient points, ``F`` free space and ``P`` physics (``LO+CS``: collisions and salient points,
components in any order); ``E`` (edges) and ``O`` (optical flow) read colour images
(Ballan et al. 2012: ``E+C+O+S`` on colour views, ``LO+E`` on RGB-D); ``S`` is the
fingertips detected in depth when the energy has ``LO``, the nails detected in colour
views (:mod:`~torchhand.tracking.energies.nails`) when it has not; anatomy,
regularisation and the chain smoothness of ropes are always added.
"""

from __future__ import annotations

from typing import List, Optional

from torchhand.tracking.energies import (anatomy, chain_smoothness, collision, data_to_model, edges, free_space,
                                         keypoints, nails, optical_flow, physics, regularization)
from torchhand.tracking.energies.edges import Edges
from torchhand.tracking.energies.nails import Nails
from torchhand.tracking.energies.optical_flow import OpticalFlow
from torchhand.tracking.energies.anatomy import Anatomy
from torchhand.tracking.energies.base import Counts, EnergyTerm, Prepared, Residuals, TrackState, counts
from torchhand.tracking.energies.chain_smoothness import ChainSmoothness
from torchhand.tracking.energies.collision import Collision
from torchhand.tracking.energies.data_to_model import DataToModel
from torchhand.tracking.energies.free_space import FreeSpace
from torchhand.tracking.energies.keypoints import Keypoints
from torchhand.tracking.energies.model_to_data import ModelToData
from torchhand.tracking.energies.physics import Physics
from torchhand.tracking.energies.regularization import Regularization
from torchhand.tracking.energies.salient_points import Salient
from torchhand.tracking.energies.wrappers import Robust, Weighted

__all__ = ["EnergyTerm", "Residuals", "Counts", "counts", "Prepared", "TrackState", "ModelToData", "DataToModel", "Collision", "Salient",
           "Keypoints", "FreeSpace", "Physics", "Edges", "OpticalFlow", "Nails", "Anatomy", "Regularization", "ChainSmoothness",
           "Weighted", "Robust", "parse_energy", "default_data_to_model", "default_free_space", "default_priors",
           "ENERGY_COMPONENTS"]

#: components understood by parse_energy after ``LO``
ENERGY_COMPONENTS = {"E": "edges of colour images (rendered occluding contours to Canny edges, DCH-Thres)",
                     "O": "optical flow of colour images (visible vertices follow the DIS flow)",
                     "C": "collisions (conic distance fields, Eq. 4.9-4.13)",
                     "S": "salient points (with LO: fingertips detected in depth, Eq. 4.14-4.15; without: "
                          "nails detected in colour views, Ballan Eq. 3)",
                     "F": "free space (model surface where the sensor saw nothing or farther, pulled into its data)",
                     "P": "physics (Bullet stability of held rigid objects, Eq. 4.16; needs pybullet)",
                     "K": "keypoints (the model's 21 joints pulled onto the hand localiser's, robust, "
                          "confidence-weighted; docs/localiser.md)"}


def default_data_to_model(**kwargs) -> EnergyTerm:
    """The tracker's data-to-model term: Cauchy loss with a misfit-following scale,
    weight 0.25 (:mod:`torchhand.tracking.energies.data_to_model`)."""
    return Weighted(Robust(DataToModel(**kwargs), data_to_model.DEFAULT_LOSS), data_to_model.DEFAULT_WEIGHT)


def default_free_space(**kwargs) -> EnergyTerm:
    """The tracker's free-space term: Cauchy loss, scale 5 mm, weight 0.25
    (:mod:`torchhand.tracking.energies.free_space`)."""
    return Weighted(Robust(FreeSpace(**kwargs), free_space.DEFAULT_LOSS), free_space.DEFAULT_WEIGHT)


def default_priors() -> List[EnergyTerm]:
    """Anatomy (gamma_a = 0.0015 C_all), regularisation (gamma_r = 0.02 C_all) and the
    chain smoothness of ropes (0.2 C_all; no residuals in scenes without such chains)."""
    return [Weighted(Anatomy(), anatomy.DEFAULT_WEIGHT, per_correspondence=True),
            Weighted(Regularization(), regularization.DEFAULT_WEIGHT, per_correspondence=True),
            Weighted(ChainSmoothness(), chain_smoothness.DEFAULT_WEIGHT, per_correspondence=True)]


def parse_energy(spec: str, metric: str = "point-to-plane", backend: Optional[str] = None) -> List[EnergyTerm]:
    """Terms for an energy string: ``LO``, ``LO+C``, ``LO+S``, ``LO+F``, ``LO+CSF``, ``E+C+O``, ``LO+E``...;
    ``backend``: of the data terms' neighbour searches (``"warp"`` or ``"torch"``; None: Warp when
    installed)."""
    parts = [p for p in spec.replace(" ", "").split("+")]
    if not spec.strip() or any(not p for p in parts):
        raise ValueError(f"energy {spec!r}: expected parts joined by '+', e.g. LO+C or E+C+O")
    lo = parts.count("LO")
    if lo > 1:
        raise ValueError(f"energy {spec!r} names LO twice")
    extra = "".join(p for p in parts if p != "LO")
    unknown = [c for c in extra if c not in ENERGY_COMPONENTS]
    if unknown:
        raise ValueError(f"energy {spec!r}: unknown components {unknown}; known: LO and {sorted(ENERGY_COMPONENTS)}")
    if len(set(extra)) != len(extra):
        raise ValueError(f"energy {spec!r} names a component twice")
    if not lo and not set(extra) & set("ESFO"):
        raise ValueError(f"energy {spec!r} has no data term: give LO (depth) or E / O (colour), e.g. LO+C or E+C+O")
    terms: List[EnergyTerm] = []
    if lo:
        terms += [ModelToData(metric=metric, backend=backend), default_data_to_model(backend=backend)]
    if "E" in extra:
        terms.append(Robust(Edges(backend=backend), edges.DEFAULT_LOSS))
    if "O" in extra:
        terms.append(Weighted(Robust(OpticalFlow(), optical_flow.DEFAULT_LOSS), optical_flow.DEFAULT_WEIGHT))
    if "C" in extra:
        terms.append(Weighted(Collision(), collision.DEFAULT_WEIGHT))
    if "S" in extra:  # fingertips in depth with the depth terms, else the nails of colour views
        terms.append(Salient() if lo else Weighted(Robust(Nails(), nails.DEFAULT_LOSS), nails.DEFAULT_WEIGHT))
    if "F" in extra:
        terms.append(default_free_space(backend=backend))
    if "P" in extra:
        terms.append(Weighted(Physics(), physics.DEFAULT_WEIGHT))
    if "K" in extra:
        terms.append(Weighted(Robust(Keypoints(), keypoints.DEFAULT_LOSS), keypoints.DEFAULT_WEIGHT))
    return terms + default_priors()

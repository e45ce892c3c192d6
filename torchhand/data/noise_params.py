"""The parameters of the structured-light (Kinect v1 / Primesense Carmine) noise model.

:class:`KinectNoise` holds every parameter of :func:`torchhand.data.noise.apply_kinect_noise`
with its source, and the model's terms (axial and lateral standard deviations, the
quantisation step); :data:`NOISE_MODELS` names the models a configuration can choose.
The model is described in ``docs/noise.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional

import torch

__all__ = ["KinectNoise", "NOISE_MODELS", "noise_model"]


@dataclass(frozen=True)
class KinectNoise:
    """Parameters of the Kinect-v1-type structured-light noise model.

    Every effect can be switched off on its own (see each attribute). Defaults describe
    a Kinect v1 / Primesense Carmine 1.08-1.09 at 640x480 (VGA).

    Disparity model (Khoshelham & Elberink 2012, "Accuracy and resolution of Kinect
    depth data for indoor mapping applications", Sensors 12(2):1437-1454; Smisek,
    Jancosek & Pajdla 2011, "3D with Kinect", ICCV Workshops). Depth is triangulated
    from the disparity ``d = f * b / z`` between the projected speckle pattern and the
    IR image, measured to 1/8 px, so depth comes in steps of ``z**2 / (f * b) / 8``:

    Attributes:
        baseline_mm: projector-camera baseline ``b``, 75 mm (Khoshelham & Elberink
            2012, sec. 2; Smisek et al. 2011 report about 75 mm as well). Also sets the
            width of the projector shadows.
        focal_px: focal length ``f`` (px) of the disparity model. None (default) uses
            ``fx`` of the ``K`` passed to :func:`apply_kinect_noise` (525 px for the
            thesis camera), so quantisation steps are consistent with the image. The
            Kinect's own IR camera has ``f`` of about 580-585 px (Khoshelham & Elberink
            2012; Smisek et al. 2011); set it to model that camera exactly.
        disparity_resolution_px: sub-pixel disparity resolution, 1/8 px (Khoshelham &
            Elberink 2012, sec. 3: the normalised disparity is stored in 1/8 px units;
            Smisek et al. 2011). 0 disables quantisation.
        compensate_quantisation: Nguyen et al.'s axial sigma was measured on real,
            already quantised depth. If True (default) the Gaussian noise added before
            quantisation has variance ``sigma_z**2 - q**2 / 12`` (q the local
            quantisation step; floored at ``(sigma_z / 2)**2``), so that the *total*
            standard deviation after quantisation is about ``sigma_z``. If False the
            Gaussian has ``sigma_z`` and the output is slightly noisier.

    Axial noise (Nguyen, Izadi & Lovell 2012, "Modeling Kinect sensor noise for improved
    3D reconstruction and tracking", 3DIMPVT, eq. for ``sigma_z``), with ``z`` in metres
    and ``theta`` the angle between the surface normal and the viewing ray::

        sigma_z [mm] = 1.2 + 1.9 (z - 0.4)**2 + 0.1 / sqrt(z) * theta**2 / (pi/2 - theta)**2

    Attributes:
        axial_sigma0_mm: constant term, 1.2 mm (Nguyen et al. 2012).
        axial_sigma_quad_mm: quadratic coefficient, 1.9 mm/m^2 (Nguyen et al. 2012).
        axial_z0_m: depth of the quadratic's vertex, 0.4 m (Nguyen et al. 2012).
        axial_sigma_angle_mm: angular coefficient, 0.1 mm*sqrt(m) (Nguyen et al.
            2012). All three sigma coefficients 0 disables axial noise.

    Lateral noise (Nguyen et al. 2012, eq. for ``sigma_L``)::

        sigma_L [px] = 0.8 + 0.035 * theta / (pi/2 - theta)

    (i.e. ``sigma_L [mm] = sigma_L [px] * z / f``). It is applied as an independent
    per-pixel, per-axis Gaussian shift of the position where the clean depth is
    sampled, rounded to whole pixels (nearest-neighbour sampling), so edges become
    jagged but no depth value that was not in the input is invented. Nguyen et al.
    measured ``sigma_L`` as the scatter of *edge* pixels; on a smooth surface a shift
    would only add ``slope * shift`` of extra axial noise, which their ``sigma_z`` (fit
    on tilted planes) already contains. So a pixel takes the shifted sample only if it
    differs from its own depth by more than ``lateral_min_jump_mm``. Shifts are clamped
    to 4 px (5.6 ``sigma_L`` at normal incidence, 4 ``sigma_L`` at 75 degrees).

    Attributes:
        lateral_sigma0_px: constant term, 0.8 px (Nguyen et al. 2012). Both lateral
            coefficients 0 disables lateral noise.
        lateral_sigma_angle_px: angular coefficient, 0.035 px (Nguyen et al. 2012).
        lateral_min_jump_mm: depth difference (mm) above which the shifted sample is
            taken, 10 mm (the renderer's silhouette-edge threshold; a modelling choice,
            no literature value). 0 applies the shift everywhere.

    Projector shadows: the projector sits ``baseline_mm`` beside the IR camera, so
    surfaces the camera sees but the projector does not (a band on the far side of an
    occluding edge, ``f * b * (1/z_near - 1/z_far)`` px wide) get no pattern and no
    depth. Qualitatively documented by Khoshelham & Elberink 2012 and Smisek et al.
    2011; modelled here exactly per image row (see :func:`apply_kinect_noise`).

    Attributes:
        shadows: enable projector shadows.
        projector_on_right: True (default) if the projector is at ``+x`` of the camera
            (to the right in the image). On the Kinect v1 the IR emitter and IR camera
            are at opposite ends of the bar, the emitter at the sensor's own right
            (the viewer's left when facing the device), which puts the shadows on the
            *left* side of foreground objects in the (un-mirrored) depth image.
        shadow_tolerance_px: a pixel is shadowed only if the occluder overlaps its
            projector ray by more than this (px); absorbs ray-casting round-off.

    Grazing-angle dropout: the reflected pattern becomes too weak and too stretched to
    correlate at grazing incidence. Nguyen et al. 2012's angle terms grow without bound
    as the angle approaches 90 degrees and their measurements cover moderate angles
    only; the ramp below (start and end angles) is a heuristic, not from the paper.

    Attributes:
        grazing_start_deg: angle (deg) at which dropout begins, 70.
        grazing_full_deg: angle (deg) from which every pixel is dropped, 85; the drop
            probability ramps linearly in between. ``grazing_start_deg >= 90`` disables.

    Random holes (heuristic, no measured source: small blobs of missing data from
    specular or dark spots and pattern-matching failures, as seen in Kinect v1 frames):

    Attributes:
        holes_per_frame: mean (Poisson) number of holes per frame, 4. 0 disables.
        hole_radius_min_px: smallest hole radius, 1 px.
        hole_radius_max_px: largest hole radius, 3 px (radii uniform in between).

    Range (Kinect v1 "near mode" minimum and default-mode maximum, Microsoft Kinect for
    Windows documentation; Khoshelham & Elberink 2012 use 0.5-5 m; the Carmine 1.09
    datasheet gives 0.35-1.4 m, set ``max_depth_mm=1400`` to model it):

    Attributes:
        min_depth_mm: nearer measurements become 0, 400 mm.
        max_depth_mm: farther measurements become 0, 4000 mm.
    """

    baseline_mm: float = 75.0
    focal_px: Optional[float] = None
    disparity_resolution_px: float = 1.0 / 8.0
    compensate_quantisation: bool = True
    axial_sigma0_mm: float = 1.2
    axial_sigma_quad_mm: float = 1.9
    axial_z0_m: float = 0.4
    axial_sigma_angle_mm: float = 0.1
    lateral_sigma0_px: float = 0.8
    lateral_sigma_angle_px: float = 0.035
    lateral_min_jump_mm: float = 10.0
    shadows: bool = True
    projector_on_right: bool = True
    shadow_tolerance_px: float = 0.25
    grazing_start_deg: float = 70.0
    grazing_full_deg: float = 85.0
    holes_per_frame: float = 4.0
    hole_radius_min_px: int = 1
    hole_radius_max_px: int = 3
    min_depth_mm: float = 400.0
    max_depth_mm: float = 4000.0

    def __post_init__(self) -> None:
        def finite(name: str, lo: float = 0.0, strict: bool = False) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"KinectNoise.{name} must be a finite number, got {value!r}")
            if value < lo or (strict and value == lo):
                raise ValueError(f"KinectNoise.{name} must be {'>' if strict else '>='} {lo}, got {value!r}")

        finite("baseline_mm", strict=True)
        if self.focal_px is not None:
            finite("focal_px", strict=True)
        for name in (
            "disparity_resolution_px",
            "axial_sigma0_mm",
            "axial_sigma_quad_mm",
            "axial_z0_m",
            "axial_sigma_angle_mm",
            "lateral_sigma0_px",
            "lateral_sigma_angle_px",
            "lateral_min_jump_mm",
            "shadow_tolerance_px",
            "grazing_start_deg",
            "holes_per_frame",
            "min_depth_mm",
        ):
            finite(name)
        finite("grazing_full_deg")
        if self.grazing_full_deg <= self.grazing_start_deg and self.grazing_start_deg < 90.0:
            raise ValueError(
                f"KinectNoise.grazing_full_deg ({self.grazing_full_deg}) must exceed grazing_start_deg "
                f"({self.grazing_start_deg})"
            )
        for name in ("hole_radius_min_px", "hole_radius_max_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"KinectNoise.{name} must be an int >= 0, got {value!r}")
        if self.hole_radius_max_px < self.hole_radius_min_px:
            raise ValueError(
                f"KinectNoise.hole_radius_max_px ({self.hole_radius_max_px}) must be >= hole_radius_min_px "
                f"({self.hole_radius_min_px})"
            )
        finite("max_depth_mm", strict=True)
        if self.max_depth_mm <= self.min_depth_mm:
            raise ValueError(
                f"KinectNoise.max_depth_mm ({self.max_depth_mm}) must exceed min_depth_mm ({self.min_depth_mm})"
            )

    # ------------------------------------------------------------------ model terms

    def axial_sigma(self, z_mm, angle=0.0):
        """Axial standard deviation (mm) at depth ``z_mm`` (mm) and incidence ``angle`` (rad).

        Works on floats and tensors (Nguyen et al. 2012). Angles are clamped just
        below pi/2 so the result stays finite.
        """
        z_m = z_mm / 1000.0
        if isinstance(z_m, torch.Tensor) or isinstance(angle, torch.Tensor):
            z_m = torch.as_tensor(z_m)
            angle = torch.as_tensor(angle, dtype=z_m.dtype, device=z_m.device).clamp(0.0, _MAX_ANGLE)
            ratio = angle / (math.pi / 2 - angle)
            return (
                self.axial_sigma0_mm
                + self.axial_sigma_quad_mm * (z_m - self.axial_z0_m) ** 2
                + self.axial_sigma_angle_mm * ratio**2 / z_m.clamp_min(1e-6).sqrt()
            )
        angle = min(max(float(angle), 0.0), _MAX_ANGLE)
        ratio = angle / (math.pi / 2 - angle)
        return (
            self.axial_sigma0_mm
            + self.axial_sigma_quad_mm * (z_m - self.axial_z0_m) ** 2
            + self.axial_sigma_angle_mm * ratio**2 / math.sqrt(max(z_m, 1e-6))
        )

    def lateral_sigma_px(self, angle=0.0):
        """Lateral standard deviation (px) at incidence ``angle`` (rad), Nguyen et al. 2012."""
        if isinstance(angle, torch.Tensor):
            angle = angle.clamp(0.0, _MAX_ANGLE)
            return self.lateral_sigma0_px + self.lateral_sigma_angle_px * angle / (math.pi / 2 - angle)
        angle = min(max(float(angle), 0.0), _MAX_ANGLE)
        return self.lateral_sigma0_px + self.lateral_sigma_angle_px * angle / (math.pi / 2 - angle)

    def quantisation_step(self, z_mm, focal_px: float):
        """Depth step (mm) between neighbouring disparity levels at ``z_mm``: ``z^2 / (f b) * res``."""
        f = self.focal_px if self.focal_px is not None else focal_px
        return z_mm**2 / (f * self.baseline_mm) * self.disparity_resolution_px


#: Angles are clamped to this (rad) inside the sigma formulas (89.5 deg).
_MAX_ANGLE = math.radians(89.5)


#: Named noise models; ``None`` means clean depth.
NOISE_MODELS: Dict[str, Optional[KinectNoise]] = {"none": None, "kinect": KinectNoise()}


def noise_model(name: str) -> Optional[KinectNoise]:
    """The noise parameters registered as ``name`` in :data:`NOISE_MODELS` (None for "none").

    Raises:
        ValueError: for unknown names, listing the valid ones.
    """
    if not isinstance(name, str):
        raise TypeError(f"noise model name must be a str, got {type(name).__name__}")
    try:
        return NOISE_MODELS[name]
    except KeyError:
        valid = ", ".join(repr(k) for k in NOISE_MODELS)
        raise ValueError(f"unknown noise model {name!r}; valid names: {valid}") from None

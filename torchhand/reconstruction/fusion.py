"""Depth fusion and the surface of a scanned object (thesis Sec. 5.4.2.1).

The object's depth is fused into a truncated signed distance function (TSDF, Curless
and Levoy 1996; open3d's ``ScalableTSDFVolume``) in the object's frame; its surface
is extracted by marching cubes, tiny disconnected components are removed, the mesh
is smoothed (Laplacian) and closed by screened Poisson reconstruction (Kazhdan 2006;
open3d), which gives a watertight mesh also where the fingers always covered the
object; the mesh is then simplified (quadric decimation) when that keeps it closed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

__all__ = ["FusionConfig", "TSDF", "SurfaceMesh", "extract_surface"]


@dataclass(frozen=True)
class FusionConfig:
    """voxel: mm (the thesis: 350 mm at 256 voxels, 1.4 mm); truncation: mm of the
    signed distance; poisson_depth: octree depth of the Poisson reconstruction (the
    thesis: 10); triangles: the simplified mesh's target size; min_component: faces
    of the smallest component kept, as a fraction of the largest."""

    voxel: float = 1.5
    truncation: float = 6.0
    poisson_depth: int = 8
    smoothing: int = 3
    triangles: int = 6000
    min_component: float = 0.05


class SurfaceMesh(NamedTuple):
    """vertices: (V, 3) float64 mm; faces: (F, 3) int64; watertight: a closed
    2-manifold; raw_faces: faces of the marching-cubes mesh before closing."""

    vertices: np.ndarray
    faces: np.ndarray
    watertight: bool
    raw_faces: int


class TSDF:
    """A TSDF volume in the object frame, integrating depth maps (mm) seen from poses."""

    def __init__(self, K: np.ndarray, width: int, height: int, config: FusionConfig = FusionConfig()):
        import open3d as o3d

        self.config = config
        self.volume = o3d.pipelines.integration.ScalableTSDFVolume(
            voxel_length=config.voxel, sdf_trunc=config.truncation,
            color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor)
        self.intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, float(K[0, 0]), float(K[1, 1]),
                                                          float(K[0, 2]), float(K[1, 2]))
        self.frames = 0

    def integrate(self, depth_mm: np.ndarray, object_to_camera: np.ndarray) -> None:
        """Fuse one depth map (H, W) float mm (0 or NaN: nothing) seen with the object at
        ``object_to_camera`` (4, 4)."""
        import open3d as o3d

        d = np.nan_to_num(np.asarray(depth_mm, np.float32), nan=0.0)
        depth = o3d.geometry.Image(d)
        colour = o3d.geometry.Image(np.zeros(d.shape + (3,), np.uint8))
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(colour, depth, depth_scale=1.0, depth_trunc=1e5,
                                                                  convert_rgb_to_intensity=False)
        self.volume.integrate(rgbd, self.intrinsic, np.asarray(object_to_camera, np.float64))
        self.frames += 1

    def surface(self) -> SurfaceMesh:
        """The closed surface of what was fused (:func:`extract_surface`)."""
        return extract_surface(self.volume.extract_triangle_mesh(), self.config)


def extract_surface(mesh, config: FusionConfig = FusionConfig()) -> SurfaceMesh:
    """Marching-cubes mesh (open3d ``TriangleMesh``) -> the closed, simplified surface."""
    import open3d as o3d
    import trimesh

    raw = len(mesh.triangles)
    if raw == 0:
        return SurfaceMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), False, 0)
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    mesh.remove_triangles_by_mask(counts[labels] < config.min_component * counts.max())
    mesh.remove_unreferenced_vertices()
    if config.smoothing:
        mesh = mesh.filter_smooth_laplacian(config.smoothing)
    mesh.compute_vertex_normals()
    cloud = o3d.geometry.PointCloud(mesh.vertices)
    cloud.normals = mesh.vertex_normals
    # scale 2: the octree's cube is twice the samples' box, so the surface Poisson closes
    # over the never-seen side (where the fingers hold it) is not clipped by the cube; one
    # thread: Open3D's multi-threaded Poisson crashes at random under load (isl-org/Open3D#6828)
    closed, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=config.poisson_depth,
                                                                          scale=2.0, n_threads=1)
    best = _largest_component(closed)
    if config.triangles and len(best.faces) > config.triangles:
        simple = closed.simplify_quadric_decimation(config.triangles)
        small = _largest_component(simple)
        if small.is_watertight:
            best = small
    v, f = np.asarray(best.vertices, np.float64), np.asarray(best.faces, np.int64)
    ok = bool(best.is_watertight)
    if not ok:  # close what is left open
        trimesh.repair.fill_holes(best)
        ok = bool(best.is_watertight)
        v, f = np.asarray(best.vertices, np.float64), np.asarray(best.faces, np.int64)
    return SurfaceMesh(v, f, ok, raw)


def _largest_component(o3d_mesh):
    import trimesh

    tm = trimesh.Trimesh(np.asarray(o3d_mesh.vertices), np.asarray(o3d_mesh.triangles), process=True)
    parts = tm.split(only_watertight=False)
    if len(parts) > 1:
        tm = max(parts, key=lambda p: len(p.faces))
    if tm.volume < 0:
        tm.invert()
    return tm

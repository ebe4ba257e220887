"""An embedded synthetic scene: a textureless mug on a table with its handle hidden.

Everything is generated offline with open3d's ``RaycastingScene``: a mug (hollow cylinder body
plus a torus handle; object frame: axis +z, handle along +x, origin at the body centre, like
YCB-Video's ``025_mug``) stands on a table plane; a box between the camera and the handle hides
the handle, so the mug's rotation about its own axis is ambiguous from the image (the paper's
figure 1). Colours are grey Lambertian shading from the surface normals (no texture).

World frame of the scene: the table is the plane ``z = 0``, ``+z`` up.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from certpose.geometry.rgbd import CameraIntrinsics, RGBDFrame
from solvers.lie import invert_transform, make_transform
from solvers.validation import resolve_rng

__all__ = ["SyntheticScene", "make_mug_scene", "mug_parts", "look_at", "render_depth"]

log = logging.getLogger(__name__)

# Mug geometry, metres (object frame: axis +z, handle +x, origin at the body centre).
MUG_RADIUS = 0.040
MUG_INNER_RADIUS = 0.0365
MUG_HEIGHT = 0.100
MUG_BOTTOM = 0.006
HANDLE_CENTER_X = 0.038
HANDLE_RING_RADIUS = 0.022
HANDLE_TUBE_RADIUS = 0.006

_ALBEDO = {"body": 0.85, "handle": 0.85, "table": 0.55, "occluder": 0.7}


def _lathe(profile: NDArray[np.float64], segments: int) -> Any:
    """Triangle mesh of the surface of revolution of an ``(r, z)`` polyline about ``z``."""
    import open3d as o3d

    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    vertices, rings = [], []
    for r, z in profile:
        start = sum(len(ring) for ring in rings)
        if r <= 0:
            vertices.append([[0.0, 0.0, z]])
            rings.append(np.array([start]))
        else:
            vertices.append(np.stack([r * np.cos(angles), r * np.sin(angles), np.full(segments, z)], 1))
            rings.append(start + np.arange(segments))
    tris = []
    nxt = np.roll(np.arange(segments), -1)
    for a, b in zip(rings[:-1], rings[1:], strict=True):
        if a.size == 1:
            tris.append(np.stack([np.full(segments, a[0]), b, b[nxt]], 1))
        elif b.size == 1:
            tris.append(np.stack([a, np.full(segments, b[0]), a[nxt]], 1))
        else:
            tris.append(np.stack([a, b, b[nxt]], 1))
            tris.append(np.stack([a, b[nxt], a[nxt]], 1))
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.concatenate(vertices)),
        o3d.utility.Vector3iVector(np.concatenate(tris).astype(np.int32)),
    )
    return mesh


def mug_parts() -> dict[str, Any]:
    """The mug's ``"body"`` and ``"handle"`` meshes (open3d legacy) in the object frame."""
    import open3d as o3d

    h = MUG_HEIGHT / 2
    # Outer bottom centre -> outer wall -> rim -> inner wall -> inner bottom centre.
    profile = np.array(
        [
            [0.0, -h],
            [MUG_RADIUS, -h],
            [MUG_RADIUS, h],
            [MUG_INNER_RADIUS, h],
            [MUG_INNER_RADIUS, -h + MUG_BOTTOM],
            [0.0, -h + MUG_BOTTOM],
        ]
    )
    body = _lathe(profile, 96)
    handle = o3d.geometry.TriangleMesh.create_torus(
        torus_radius=HANDLE_RING_RADIUS,
        tube_radius=HANDLE_TUBE_RADIUS,
        radial_resolution=60,
        tubular_resolution=16,
    )
    # The torus ring lies in the xy-plane: turn it into the xz-plane, then move it to +x.
    handle.rotate(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), center=np.zeros(3))
    handle.translate([HANDLE_CENTER_X, 0.0, 0.0])
    # Drop the part inside the body; the cut ends stay inside the wall (R_in < x < R).
    v = np.asarray(handle.vertices)
    handle.remove_vertices_by_mask(v[:, 0] < MUG_INNER_RADIUS + 0.001)
    for mesh in (body, handle):
        mesh.compute_vertex_normals()
    return {"body": body, "handle": handle}


def _mug_mesh() -> Any:
    parts = mug_parts()
    mesh = parts["body"] + parts["handle"]
    mesh.compute_vertex_normals()
    return mesh


def look_at(eye: NDArray[np.float64], target: NDArray[np.float64], up: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """``T_world_camera`` of an OpenCV camera (x right, y down, z forward) at ``eye`` looking at ``target``."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("`up` is parallel to the viewing direction.")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    return make_transform(np.stack([right, down, forward], axis=1), eye)


def _pixel_rays(intrinsics: CameraIntrinsics, T_world_camera: NDArray[np.float64],
                v0: int, v1: int, u0: int, u1: int) -> NDArray[np.float64]:
    """Rays (N, 6): origin and direction, world frame, of the pixels ``[v0, v1) x [u0, u1)``,
    row-major; directions have unit z in the camera frame, so a ray's parameter is z-depth."""
    v, u = np.mgrid[v0:v1, u0:u1].astype(np.float64)
    d_cam = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                      np.ones_like(u)], -1).reshape(-1, 3)
    d_world = d_cam @ T_world_camera[:3, :3].T
    return np.hstack([np.broadcast_to(T_world_camera[:3, 3], d_world.shape), d_world])


def render_depth(
    meshes: dict[str, Any],
    intrinsics: CameraIntrinsics,
    T_world_camera: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.uint8], dict[str, NDArray[np.bool_]]]:
    """Ray-cast named meshes (world frame) from a pinhole camera.

    Returns
    -------
    depth : ndarray, shape (H, W)
        z-depth in metres, 0 where no surface is hit.
    color : ndarray of uint8, shape (H, W, 3)
        Grey Lambertian shading from the hit normals (light at the camera).
    hits : dict of str to ndarray of bool, shape (H, W)
        The pixels where each named mesh is the first hit.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = {}
    for name, mesh in meshes.items():
        ids[name] = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    H, W = intrinsics.height, intrinsics.width
    rays = _pixel_rays(intrinsics, T_world_camera, 0, H, 0, W)
    d_world = rays[:, 3:]
    ans = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    t_hit = ans["t_hit"].numpy().astype(np.float64).reshape(H, W)
    geom = ans["geometry_ids"].numpy().reshape(H, W)
    normals = ans["primitive_normals"].numpy().astype(np.float64).reshape(H, W, 3)
    hit = np.isfinite(t_hit)
    depth = np.where(hit, t_hit, 0.0)
    view = d_world.reshape(H, W, 3) / np.linalg.norm(d_world.reshape(H, W, 3), axis=-1, keepdims=True)
    lambert = np.abs(np.sum(normals * view, axis=-1))
    albedo = np.zeros((H, W))
    hits = {}
    for name, gid in ids.items():
        hits[name] = hit & (geom == gid)
        albedo[hits[name]] = _ALBEDO.get(name, 0.7)
    grey = np.where(hit, albedo * (0.2 + 0.8 * lambert), 0.0)
    color = np.repeat(np.clip(np.rint(255 * grey), 0, 255).astype(np.uint8)[..., None], 3, axis=2)
    return depth, color, hits


def _sample_surface(mesh: Any, n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """``n`` points uniformly on a triangle mesh's surface (area-weighted), deterministic in ``rng``."""
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    return (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A rendered mug scene with its ground truth.

    Attributes
    ----------
    frame : RGBDFrame
        The scene image (camera frame = world frame of the frame: ``T_world_camera`` = I).
    intrinsics : CameraIntrinsics
    T_camera_object : ndarray, shape (4, 4)
        Ground-truth pose: maps mug-model points into the camera frame.
    object_mask : ndarray of bool, shape (H, W)
        Visible mug pixels.
    model_points : ndarray, shape (N, 3)
        Points sampled uniformly on the mug surface, object frame, metres.
    T_table_camera : ndarray, shape (4, 4)
        Camera pose in the table frame (table plane ``z = 0``, ``+z`` up).
    surroundings : dict of str to open3d TriangleMesh
        The table and the occluder, table frame (:meth:`hidden_handle_arc` renders them).
    """

    frame: RGBDFrame
    intrinsics: CameraIntrinsics
    T_camera_object: NDArray[np.float64]
    object_mask: NDArray[np.bool_]
    model_points: NDArray[np.float64]
    T_table_camera: NDArray[np.float64] = field(repr=False)
    surroundings: dict[str, Any] = field(default_factory=dict, repr=False)

    def model_mesh(self) -> Any:
        """The mug as an open3d ``TriangleMesh`` in the object frame."""
        return _mug_mesh()

    def hidden_handle_arc(self, *, step: float = 0.5) -> Any:
        """The exact arc of turns of the mug about its axis that keep its handle out of sight.

        The mug at angle ``a`` is the ground truth turned by ``a`` about its own axis (the
        model's z axis through the origin): ``T_camera_object @ Rz(a)``. Its body is a surface
        of revolution, so the image at ``a`` equals the scene's wherever the handle is not
        seen: every angle is rendered (ray casting against the body, the table, the occluder
        and the turned handle, the rays of the pixels the handle can reach at any angle) and
        is free when no pixel sees the handle first. This is the set of poses that explain the
        image exactly, without any voxel or tolerance: the known answer for the rotation about
        the axis (eq. (1) can do no better than be flat on it and lower off it).

        Parameters
        ----------
        step : float
            Degrees between grid angles (> 0, at most 10; ``360 / step`` is rounded).

        Returns
        -------
        FreeSpaceArc
            ``violations`` counts the handle's pixels at each angle, ``depth`` is 0 and
            ``tolerance`` 0.
        """
        import math

        import open3d as o3d

        from certpose.model.arc import FreeSpaceArc, runs_and_reference_arc

        step = float(step)
        if not (math.isfinite(step) and 0 < step <= 10):
            raise ValueError(f"`step` must be in (0, 10] degrees, got {step}.")
        if not self.surroundings:
            raise ValueError("This scene keeps no surroundings to render (built outside make_mug_scene).")
        m = int(round(360.0 / step))
        angles = -180.0 + np.arange(m) * (360.0 / m)
        parts = mug_parts()
        T_table_object = self.T_table_camera @ self.T_camera_object
        hv = np.asarray(parts["handle"].vertices)
        c, s_ = np.cos(np.radians(angles)), np.sin(np.radians(angles))
        Rz = np.zeros((m, 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s_, s_, c, 1.0
        # The pixels the handle can reach at any angle (its vertices' projections, a margin).
        T_cam_obj = self.T_camera_object
        q = np.einsum("ij,mjk,nk->mni", T_cam_obj[:3, :3], Rz, hv).reshape(-1, 3) + T_cam_obj[:3, 3]
        K = self.intrinsics
        u = K.fx * q[:, 0] / q[:, 2] + K.cx
        v = K.fy * q[:, 1] / q[:, 2] + K.cy
        u0, u1 = max(int(np.floor(u.min())) - 2, 0), min(int(np.ceil(u.max())) + 2, K.width - 1)
        v0, v1 = max(int(np.floor(v.min())) - 2, 0), min(int(np.ceil(v.max())) + 2, K.height - 1)
        rays = o3d.core.Tensor(_pixel_rays(K, self.T_table_camera, v0, v1 + 1, u0, u1 + 1).astype(np.float32))
        body = o3d.t.geometry.TriangleMesh.from_legacy(
            o3d.geometry.TriangleMesh(parts["body"]).transform(T_table_object))
        fixed = [body] + [o3d.t.geometry.TriangleMesh.from_legacy(mesh) for mesh in self.surroundings.values()]
        visible = np.zeros(m, dtype=np.int64)
        for k in range(m):
            T = np.eye(4)
            T[:3, :3] = Rz[k]
            handle = o3d.geometry.TriangleMesh(parts["handle"]).transform(T_table_object @ T)
            scene = o3d.t.geometry.RaycastingScene()
            for mesh in fixed:
                scene.add_triangles(mesh)
            hid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(handle))
            ans = scene.cast_rays(rays)
            hit = np.isfinite(ans["t_hit"].numpy())
            visible[k] = int(np.count_nonzero(hit & (ans["geometry_ids"].numpy() == hid)))
        free = visible == 0
        arcs, arc, i0 = runs_and_reference_arc(angles, free)
        if arc is not None:
            status, message = "ok", f"handle hidden over {arc[0]:.1f}..{arc[1]:.1f} deg"
        else:
            status, message = "reference_in_free_space", f"the handle shows in {visible[i0]} pixels at angle 0"
        return FreeSpaceArc(angles, np.zeros(m), visible, free, arcs, arc, 0.0, 360.0 / m, arc is not None,
                            status, message)

    def render_object_views(
        self,
        n_views: int = 4,
        *,
        distance: float = 0.45,
        elevation_deg: float | Sequence[float] = (30.0, -30.0),
    ) -> list[RGBDFrame]:
        """Posed RGB-D views of the isolated mug (for building an object model).

        Cameras circle the mug at azimuths evenly spaced, view ``k`` at the elevation
        ``elevation_deg[k % len(elevation_deg)]`` above its equator (a number: every view at it).
        The default alternates above and below, as a scan turns the object over: views from
        above only never see the mug's bottom, and a model without its bottom is the same
        turned upside down (a bottomless tube with a handle symmetric about the equator).
        The world frame of these frames is the *object* frame (``T_world_camera`` =
        ``T_object_camera``); each frame's mask is the mug's pixels.
        """
        if int(n_views) != n_views or n_views < 1:
            raise ValueError(f"`n_views` must be a positive integer, got {n_views}.")
        elevations = np.atleast_1d(np.asarray(elevation_deg, dtype=np.float64))
        if elevations.ndim != 1 or elevations.size == 0 or not np.all(np.abs(elevations) < 90.0):
            raise ValueError(f"`elevation_deg` must be a number or a non-empty sequence of numbers in "
                             f"(-90, 90) degrees, got {elevation_deg!r}.")
        meshes = mug_parts()
        frames = []
        for k in range(int(n_views)):
            e = np.deg2rad(elevations[k % elevations.size])
            az = np.deg2rad(45.0) + 2.0 * np.pi * k / n_views
            eye = distance * np.array([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.sin(e)])
            T_object_camera = look_at(eye, np.zeros(3))
            depth, color, hits = render_depth(meshes, self.intrinsics, T_object_camera)
            mask = hits["body"] | hits["handle"]
            frames.append(RGBDFrame(color, depth, self.intrinsics, T_object_camera, mask))
        return frames


def make_mug_scene(
    *,
    rng: np.random.Generator | int | None = None,
    width: int = 640,
    height: int = 480,
    n_model_points: int = 2000,
    depth_noise: float = 0.0,
) -> SyntheticScene:
    """Render the embedded mug scene.

    Parameters
    ----------
    rng : numpy Generator, int or None
        Randomises the camera (distance 0.55-0.65 m, elevation 30-40 deg), the mug's yaw (its
        handle 65-90 deg away from the camera direction, either side), its position on the
        table, and the model-point sample. The same seed gives the same scene.
    width, height : int
        Image size; the focal length scales with the width (YCB-Video-like field of view).
    n_model_points : int
        Number of points sampled on the mug surface for ``model_points``.
    depth_noise : float
        Standard deviation (metres) of Gaussian noise added to the valid depth (default 0).

    Returns
    -------
    SyntheticScene
    """
    import open3d as o3d

    rng = resolve_rng(rng)
    if n_model_points < 1:
        raise ValueError(f"`n_model_points` must be positive, got {n_model_points}.")
    if not depth_noise >= 0:
        raise ValueError(f"`depth_noise` must be non-negative, got {depth_noise}.")
    f = 1066.8 * width / 640.0
    intrinsics = CameraIntrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    distance = rng.uniform(0.55, 0.65)
    elevation = np.deg2rad(rng.uniform(30.0, 40.0))
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    offset = np.deg2rad(rng.uniform(65.0, 90.0)) * rng.choice([-1.0, 1.0])
    yaw = azimuth + offset
    position = np.array([*rng.uniform(-0.05, 0.05, size=2), MUG_HEIGHT / 2])
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    T_table_object = make_transform(Rz, position)
    eye = position + distance * np.array(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
    )
    T_table_camera = look_at(eye, position)

    parts = mug_parts()
    body = o3d.geometry.TriangleMesh(parts["body"]).transform(T_table_object)
    handle = o3d.geometry.TriangleMesh(parts["handle"]).transform(T_table_object)
    table = o3d.geometry.TriangleMesh.create_box(1.5, 1.5, 0.02).translate(
        [position[0] - 0.75, position[1] - 0.75, -0.02]
    )

    # The occluder: a box standing between the camera and the handle, on the camera's side.
    handle_mid = T_table_object[:3, :3] @ np.array([HANDLE_CENTER_X + 0.01, 0.0, 0.0]) + position
    to_cam = eye[:2] - handle_mid[:2]
    to_cam /= np.linalg.norm(to_cam)
    gap, depth_box = 0.04, 0.03
    handle_top = position[2] + HANDLE_RING_RADIUS + HANDLE_TUBE_RADIUS
    # The camera looks down: a ray grazing the handle's top is higher by this at the box's front.
    rise = (gap + depth_box / 2) * np.tan(elevation)
    box_height = handle_top + rise + 0.01
    for box_width in np.arange(0.05, 0.20, 0.005):
        occ = o3d.geometry.TriangleMesh.create_box(depth_box, box_width, box_height)
        occ.translate([-depth_box / 2, -box_width / 2, 0.0])
        ang = np.arctan2(to_cam[1], to_cam[0])
        occ.rotate(
            np.array([[np.cos(ang), -np.sin(ang), 0.0], [np.sin(ang), np.cos(ang), 0.0], [0, 0, 1.0]]),
            center=np.zeros(3),
        )
        occ.translate([*(handle_mid[:2] + gap * to_cam), 0.0])
        meshes = {"body": body, "handle": handle, "table": table, "occluder": occ}
        depth, color, hits = render_depth(meshes, intrinsics, T_table_camera)
        if not hits["handle"].any():
            break
    else:  # pragma: no cover - the loop always finds a wide enough box for the sampled layouts
        raise RuntimeError("Could not hide the handle behind the occluder.")
    mask = hits["body"] | hits["handle"]
    if mask.sum() < 500:
        raise RuntimeError(f"Only {int(mask.sum())} mug pixels are visible; the layout failed.")
    if depth_noise > 0:
        valid = depth > 0
        depth = depth.copy()
        depth[valid] = np.maximum(depth[valid] + rng.normal(0.0, depth_noise, int(valid.sum())), 1e-3)

    T_camera_table = invert_transform(T_table_camera)
    T_camera_object = T_camera_table @ T_table_object
    model_points = _model_points(n_model_points, rng)
    frame = RGBDFrame(color, depth, intrinsics)
    return SyntheticScene(frame, intrinsics, T_camera_object, mask, model_points, T_table_camera,
                          {"table": table, "occluder": occ})


def _model_points(n: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """Surface samples of the mug; handle samples hidden inside the body wall are dropped."""
    parts = mug_parts()
    areas = {k: parts[k].get_surface_area() for k in ("body", "handle")}
    out = []
    total = sum(areas.values())
    counts = {"body": int(round(n * areas["body"] / total))}
    counts["handle"] = n - counts["body"]
    out.append(_sample_surface(parts["body"], counts["body"], rng))
    handle_pts = np.empty((0, 3))
    while handle_pts.shape[0] < counts["handle"]:
        p = _sample_surface(parts["handle"], 2 * counts["handle"] + 8, rng)
        p = p[np.hypot(p[:, 0], p[:, 1]) >= MUG_RADIUS]
        handle_pts = np.vstack([handle_pts, p])
    out.append(handle_pts[: counts["handle"]])
    return np.vstack(out)

"""Triangle meshes of a world and Open3D ray casting against them.

The static geometry (ground plane, buildings, vegetation, poles, props, parked vehicles) is
triangulated and put into one ``open3d.t.geometry.RaycastingScene`` once per scene. Moving
agents get a second, small scene per distinct time, built only when the scene has moving agents
(the agent-motion effect). A ray's hit is the nearer of the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from renderworld.sim.objects import BOX, CONE, CYLINDER, SPHERE, SimObject

__all__ = ["Hits", "Raycaster", "triangulate", "GROUND_OBJECT"]

GROUND_OBJECT = -1  # object index of ground triangles


def _templates() -> dict[int, tuple[np.ndarray, np.ndarray]]:
    import open3d as o3d

    g = o3d.geometry.TriangleMesh
    box = g.create_box(1.0, 1.0, 1.0)
    box.translate((-0.5, -0.5, -0.5))
    meshes = {
        BOX: box,
        CYLINDER: g.create_cylinder(radius=1.0, height=1.0, resolution=12, split=1),
        SPHERE: g.create_sphere(radius=1.0, resolution=6),
        CONE: g.create_cone(radius=1.0, height=1.0, resolution=12, split=1),
    }
    return {k: (np.asarray(m.vertices), np.asarray(m.triangles)) for k, m in meshes.items()}


_TEMPLATES: dict[int, tuple[np.ndarray, np.ndarray]] | None = None


def _rot(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    r = np.zeros(yaw.shape + (3, 3))
    r[..., 0, 0], r[..., 0, 1], r[..., 1, 0], r[..., 1, 1], r[..., 2, 2] = c, -s, s, c, 1.0
    return r


def triangulate(objects: list[SimObject], indices: list[int], t: float):
    """Triangles of ``objects[i]`` for ``i`` in ``indices`` at time ``t`` (scene frame).

    Returns:
        ``(vertices [V, 3] float32, triangles [T, 3] uint32, tri_object [T] int32 (index into
        objects), tri_part [T] uint8)``.
    """
    global _TEMPLATES
    if _TEMPLATES is None:
        _TEMPLATES = _templates()
    verts, tris, tobj, tpart = [], [], [], []
    offset = 0
    for i in indices:
        obj = objects[i]
        (xy,), (yaw,) = (a[None] for a in obj.trajectory.pose(t))
        pose_r = _rot(np.asarray(yaw))
        for shape in np.unique(obj.shape):
            sel = np.nonzero(obj.shape == shape)[0]
            tv, tt = _TEMPLATES[int(shape)]
            dims = obj.dims[sel]
            scale = dims.copy()
            if shape != BOX:
                scale[:, :2] = dims[:, :2] / 2
            if shape == SPHERE:
                scale[:, 2] = dims[:, 2] / 2
            local = tv[None] * scale[:, None, :]  # [P, n, 3]
            local = np.einsum("pij,pnj->pni", _rot(obj.yaw[sel]), local) + obj.centre[sel, None]
            world = local @ pose_r.T + np.array([xy[0], xy[1], 0.0])
            n = tv.shape[0]
            for k in range(len(sel)):
                verts.append(world[k])
                tris.append(tt + offset)
                offset += n
                tobj.append(np.full(len(tt), i, dtype=np.int32))
                tpart.append(np.full(len(tt), obj.part[sel[k]], dtype=np.uint8))
    if not verts:
        return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32),
                np.zeros(0, np.int32), np.zeros(0, np.uint8))  # fmt: skip
    return (
        np.concatenate(verts).astype(np.float32),
        np.concatenate(tris).astype(np.uint32),
        np.concatenate(tobj),
        np.concatenate(tpart),
    )


@dataclass
class Hits:
    """Ray-cast results for N rays (scene frame).

    Attributes:
        t: [N] float32 distance along the (unit) ray, metres; ``inf`` on a miss.
        obj: [N] int32 object index; ``GROUND_OBJECT`` for the ground; -2 on a miss.
        part: [N] uint8 shading part.
        normal: [N, 3] float32 unit surface normal facing the ray origin.
    """

    t: np.ndarray
    obj: np.ndarray
    part: np.ndarray
    normal: np.ndarray


class _Scene:
    def __init__(self, verts, tris, tobj, tpart):
        import open3d as o3d

        self.scene = o3d.t.geometry.RaycastingScene()
        self.tobj, self.tpart = tobj, tpart
        self.empty = len(tris) == 0
        if not self.empty:
            self.scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))

    def cast(self, rays: np.ndarray) -> Hits:
        import open3d as o3d

        n = len(rays)
        if self.empty:
            return Hits(np.full(n, np.inf, np.float32), np.full(n, -2, np.int32),
                        np.zeros(n, np.uint8), np.zeros((n, 3), np.float32))  # fmt: skip
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        prim = np.where(hit, prim, 0)
        return Hits(
            t=t,
            obj=np.where(hit, self.tobj[prim], -2).astype(np.int32),
            part=np.where(hit, self.tpart[prim], 0).astype(np.uint8),
            normal=ans["primitive_normals"].numpy(),
        )


class Raycaster:
    """Casts rays against a world's static scene plus its moving agents at a given time.

    Args:
        objects: every object of the world.
        ground_extent: (xmin, ymin, xmax, ymax) of the ground plane, metres.
    """

    def __init__(self, objects: list[SimObject], ground_extent: tuple[float, float, float, float]):
        self.objects = objects
        static = [i for i, o in enumerate(objects) if not o.moving]
        self.moving = [i for i, o in enumerate(objects) if o.moving]
        v, f, o, p = triangulate(objects, static, 0.0)
        x0, y0, x1, y1 = ground_extent
        gv = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float32)
        gt = np.array([[0, 1, 2], [0, 2, 3]], np.uint32) + len(v)
        self.static = _Scene(
            np.concatenate([v, gv]),
            np.concatenate([f, gt]),
            np.concatenate([o, np.full(2, GROUND_OBJECT, np.int32)]),
            np.concatenate([p, np.zeros(2, np.uint8)]),
        )
        self._dynamic: dict[float, _Scene] = {}
        self.dynamic_builds = 0

    def dynamic(self, t: float) -> _Scene | None:
        """The moving agents' scene at time ``t`` (cached); None when nothing moves."""
        if not self.moving:
            return None
        key = round(float(t), 6)
        if key not in self._dynamic:
            if len(self._dynamic) > 16:
                self._dynamic.clear()
            self._dynamic[key] = _Scene(*triangulate(self.objects, self.moving, key))
            self.dynamic_builds += 1
        return self._dynamic[key]

    def cast(self, origins: np.ndarray, dirs: np.ndarray, t: float) -> Hits:
        """Cast rays from ``origins`` [N, 3] along unit ``dirs`` [N, 3] (scene frame) at ``t`` s."""
        rays = np.concatenate(
            [np.broadcast_to(origins, dirs.shape), dirs], axis=1, dtype=np.float32
        )
        hits = self.static.cast(rays)
        dyn = self.dynamic(t)
        if dyn is not None:
            other = dyn.cast(rays)
            closer = other.t < hits.t
            hits = Hits(
                np.where(closer, other.t, hits.t),
                np.where(closer, other.obj, hits.obj),
                np.where(closer, other.part, hits.part),
                np.where(closer[:, None], other.normal, hits.normal),
            )
        flip = (hits.normal * dirs).sum(1) > 0
        hits.normal[flip] *= -1
        return hits

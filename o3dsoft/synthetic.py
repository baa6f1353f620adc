"""Synthetic objects for training on scan-like pairs: random meshes, sampled on their outer surface.

ModelNet40's release has 1,024 points per shape, so two views of one of its halves hold a few
hundred points each, sparser than the 1,024-point samples the network gets of a scan. These
objects have any density: each is a random assembly of 1-4 parts (smooth blobs, boxes, cylinders,
capsules, cones, tori), and its points are where rays from cameras all around it first hit it, so
that no point lies inside the object or on a face one part hides in another (a scan never sees
those). :func:`outer_surface` keeps a near-uniform subset, and :func:`objects` returns them in
the layout of :func:`o3dsoft.data.load_modelnet40` (radius-1 shapes), so every protocol and the
training command run on them unchanged (``benchmarks/make_shapes.py`` writes them as HDF5).
"""

from __future__ import annotations

from typing import List, Tuple

import numpy as np

from .transforms import random_rotation

# Kinds of object, the category labels of the written dataset.
KINDS: Tuple[str, ...] = ("blobs", "blocks", "mixed")
_SMOOTH, _SOLID = ("blob",), ("box", "cylinder", "capsule", "cone", "torus")


def _blob(rng: np.random.Generator):
    """A sphere whose radius varies smoothly with direction (a few random low-frequency waves)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3)
    v = mesh.vertices
    radius = np.ones(len(v))
    for _ in range(4):
        freq = rng.normal(size=3) * rng.uniform(1.0, 3.0)
        radius += rng.uniform(0.05, 0.25) * np.cos(v @ freq + rng.uniform(0, 2 * np.pi))
    mesh.vertices = v * np.clip(radius, 0.3, None)[:, None]
    return mesh


def _part(kind: str, rng: np.random.Generator):
    """One part of unit size, before its random stretch, turn and place."""
    import trimesh

    if kind == "blob":
        return _blob(rng)
    if kind == "box":
        return trimesh.creation.box(extents=rng.uniform(0.3, 1.5, size=3))
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=rng.uniform(0.2, 0.6), height=rng.uniform(0.5, 2.0), sections=24)
    if kind == "capsule":
        return trimesh.creation.capsule(radius=rng.uniform(0.2, 0.5), height=rng.uniform(0.3, 1.5), count=[16, 16])
    if kind == "cone":
        return trimesh.creation.cone(radius=rng.uniform(0.3, 0.8), height=rng.uniform(0.5, 1.5), sections=24)
    return trimesh.creation.torus(major_radius=0.6, minor_radius=rng.uniform(0.1, 0.3), major_sections=24, minor_sections=12)


def random_object(rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray, int]:
    """A random assembly of 1-4 parts: (V, 3) vertices and (F, 3) triangles of the parts together
    (they may intersect), centred and scaled into the unit sphere, and its kind (index in KINDS)."""
    kind = int(rng.integers(len(KINDS)))
    pool = {0: _SMOOTH, 1: _SOLID, 2: _SMOOTH + _SOLID}[kind]
    vertices, faces, offset = [], [], 0
    for i in range(int(rng.integers(1, 5))):
        mesh = _part(pool[int(rng.integers(len(pool)))], rng)
        v = (mesh.vertices * rng.uniform(0.5, 1.5, size=3)) @ random_rotation(rng).T
        v = v + (0 if i == 0 else rng.uniform(-0.8, 0.8, size=3))  # parts near the first one
        vertices.append(v)
        faces.append(mesh.faces + offset)
        offset += len(v)
    v = np.concatenate(vertices)
    v = v - (v.max(axis=0) + v.min(axis=0)) / 2
    return v / np.linalg.norm(v, axis=1).max(), np.concatenate(faces), kind


def _fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit directions spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def outer_surface(vertices: np.ndarray, triangles: np.ndarray, points: int, rng: np.random.Generator, cameras: int = 14, pixels: int = 96) -> np.ndarray:
    """(points, 3) points of a mesh's outer surface, near-uniformly spread.

    Rays from `cameras` pinhole cameras around the mesh (3 radii out, 50-degree field of view,
    `pixels` x `pixels` rays each) keep the first surface each ray hits; a voxel grid then keeps
    one hit per cell, with the cell shrunk until more than `points` cells are occupied, and
    `points` of those are drawn at random.
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    hits = []
    for eye in 3.0 * _fibonacci_sphere(cameras):
        up = np.cross(eye, rng.normal(size=3))  # any direction across the view
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(50.0, [0.0, 0.0, 0.0], eye.tolist(), up.tolist(), pixels, pixels)
        t_hit = scene.cast_rays(rays)["t_hit"].numpy()
        rays = rays.numpy().reshape(-1, 6)
        t_hit = t_hit.reshape(-1)
        seen = np.isfinite(t_hit)
        hits.append(rays[seen, :3] + rays[seen, 3:] * t_hit[seen, None])
    hits = np.concatenate(hits).astype(np.float64)
    if len(hits) <= points:
        raise ValueError(f"the cameras saw {len(hits)} points of the mesh, not more than the {points} asked for")
    cell = 0.05
    while True:
        _, first = np.unique(np.floor(hits / cell).astype(np.int64), axis=0, return_index=True)
        if len(first) > points:
            return hits[rng.choice(first, size=points, replace=False)]
        cell *= 0.8


def objects(count: int, points: int, seed: int) -> Tuple[np.ndarray, np.ndarray]:
    """`count` random objects of `points` outer-surface points each: (count, points, 3) float32
    coordinates within the unit sphere and (count,) int64 kinds (indices into KINDS). Object i
    depends only on (seed, i)."""
    shapes: List[np.ndarray] = []
    kinds: List[int] = []
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        vertices, triangles, kind = random_object(rng)
        shapes.append(outer_surface(vertices, triangles, points, rng))
        kinds.append(kind)
    return np.stack(shapes).astype(np.float32), np.array(kinds, dtype=np.int64)

import numpy as np
import pytest

from benchmarks.make_shapes import write
from o3dsoft.data import get_protocol, load_modelnet40, make_pair
from o3dsoft.synthetic import KINDS, objects, outer_surface, random_object


def _two_boxes():
    """Two unit cubes, the second shifted by half its size along x: each hides a part of the other."""
    import trimesh

    a, b = trimesh.creation.box(), trimesh.creation.box()
    b.apply_translation([0.5, 0.0, 0.0])
    return np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + len(a.vertices)])


def test_the_outer_surface_has_no_point_inside_the_object():
    vertices, faces = _two_boxes()
    points = outer_surface(vertices, faces, 2000, np.random.default_rng(0))
    assert points.shape == (2000, 3)
    # On the union's boundary: on a face of a box and strictly inside neither.
    inside_a = (np.abs(points) < 0.5 - 1e-4).all(axis=1)
    inside_b = (np.abs(points - [0.5, 0.0, 0.0]) < 0.5 - 1e-4).all(axis=1)
    assert not (inside_a | inside_b).any()
    on_face = np.isclose(np.abs(points), 0.5, atol=1e-4) | np.isclose(np.abs(points - [0.5, 0, 0]), 0.5, atol=1e-4)
    assert on_face.any(axis=1).all()
    # Spread over the whole boundary (x from -0.5 to 1.0), near-uniformly: the end faces at
    # x = -0.5 and x = 1.0 hold about 1 / 7 of the boundary's area each.
    assert points[:, 0].min() == pytest.approx(-0.5, abs=1e-4) and points[:, 0].max() == pytest.approx(1.0, abs=1e-4)
    end = np.isclose(points[:, 0], -0.5, atol=1e-4).mean()
    assert 0.08 < end < 0.22


def test_random_objects_lie_in_the_unit_sphere_and_depend_only_on_seed_and_index():
    vertices, faces, kind = random_object(np.random.default_rng(3))
    assert np.linalg.norm(vertices, axis=1).max() == pytest.approx(1.0)
    assert faces.min() >= 0 and faces.max() < len(vertices) and 0 <= kind < len(KINDS)
    points, kinds = objects(3, 256, seed=5)
    assert points.shape == (3, 256, 3) and points.dtype == np.float32 and kinds.shape == (3,)
    assert np.linalg.norm(points, axis=2).max() <= 1.0 + 1e-5
    again, _ = objects(2, 256, seed=5)
    assert np.array_equal(points[:2], again)
    assert not np.array_equal(points[0], points[1])


def test_the_written_dataset_is_read_as_modelnet_and_gives_far_views(tmp_path):
    write(tmp_path, train=3, test=2, points=2048, seed=0)
    train = load_modelnet40(tmp_path, "train", points_per_shape=2048)
    test = load_modelnet40(tmp_path, "test", points_per_shape=2048)
    assert train.points.shape == (3, 2048, 3) and test.points.shape == (2, 2048, 3)
    assert train.categories == list(KINDS)
    assert not np.array_equal(train.points[0], test.points[0])  # test objects come from another seed
    assert not list(tmp_path.glob("*.partial"))
    pair = make_pair(train.points[0], get_protocol("incongruent-far-view"), seed=0, index=0)
    assert pair.source.shape == pair.target.shape == (512, 3)

import numpy as np

from o3dsoft.render import principal_plane, render_registration

from .conftest import apply, random_transform


def test_an_outdoor_scene_is_seen_from_above():
    rng = np.random.default_rng(0)
    street = rng.uniform([-60, -40, -1], [60, 40, 4], size=(5_000, 3))  # 120 m x 80 m, 5 m high
    axes = principal_plane(street)
    assert axes.shape == (3, 2) and np.allclose(axes.T @ axes, np.eye(2), atol=1e-9)
    assert np.all(np.abs(axes[2]) < 0.05)  # the view's axes are horizontal: a top-down view


def test_the_picture_is_written_whole(tmp_path):
    rng = np.random.default_rng(1)
    src = rng.normal(size=(3_000, 3)) * [2.0, 1.0, 0.2]
    T = random_transform(rng, 20.0, 0.1)
    path = render_registration(tmp_path / "pair.png", src, apply(T, src), [("input", None), ("result", T)], 0.1, "Confidence 1.00.")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
    assert [p.name for p in tmp_path.iterdir()] == ["pair.png"]  # no temporary left behind

"""Random bytes to the readers and random arrays to register: a result or one O3dsoftError,
never another exception."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import o3dsoft
from o3dsoft.errors import O3dsoftError
from o3dsoft.io import READ_EXTENSIONS, read_points

PLY_HEADER = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ext=st.sampled_from(READ_EXTENSIONS), body=st.binary(max_size=300), header=st.booleans())
def test_random_bytes_read_as_points_or_one_error(tmp_path, ext, body, header):
    path = tmp_path / f"fuzz{ext}"
    path.write_bytes((PLY_HEADER if header and ext == ".ply" else b"") + body)
    try:
        points = read_points(path, mesh_points=50)
    except O3dsoftError as e:
        assert "\n" not in str(e) and str(path) in str(e)
    else:
        assert points.ndim == 2 and points.shape[1] == 3 and len(points) > 0


values = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.floats(-10, 10))


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    source=arrays(np.float64, st.tuples(st.integers(0, 60), st.just(3)), elements=values),
    target=arrays(np.float64, st.tuples(st.integers(0, 60), st.just(3)), elements=values),
)
def test_random_arrays_register_or_one_error(tiny_model_path, source, target):
    try:
        result = o3dsoft.register(source, target, o3dsoft.RegisterConfig(weights=str(tiny_model_path)))
    except O3dsoftError as e:
        assert "\n" not in str(e)
    else:
        assert result.transformation.shape == (4, 4) and np.isfinite(result.transformation).all()

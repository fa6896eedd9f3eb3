"""ds.net.wire: exact round trips for every wire dtype and shape, and named errors for every violation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import array_shapes, arrays

from ds.net.wire import WIRE_DTYPES, TensorSpec, WireError, from_tensor, to_tensor
from protos import replay_pb2

DTYPES = ["float32", "float64", "uint8", "bool", "uint64", "int64", "int32"]


def assert_identical(a: np.ndarray, b: np.ndarray) -> None:
    assert b.dtype == a.dtype and b.shape == a.shape
    assert b.tobytes() == np.ascontiguousarray(a).tobytes()  # bit-exact, NaN payloads included


def test_every_dtype_used_is_a_wire_dtype() -> None:
    assert set(DTYPES) == WIRE_DTYPES


@settings(max_examples=150, deadline=None)
@given(
    arrays(
        dtype=st.sampled_from(DTYPES).map(np.dtype),
        shape=array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5),
    )
)
def test_round_trip_is_exact_for_every_dtype_and_shape(array: np.ndarray) -> None:
    proto = replay_pb2.Tensor.FromString(to_tensor(array).SerializeToString())
    out = from_tensor(proto)
    assert_identical(array, out)
    assert out.flags.writeable and out.flags.c_contiguous
    out[...] = out  # writable even for 0-length and 0-d arrays


@pytest.mark.parametrize("dtype", DTYPES)
def test_scalars_empty_arrays_views_and_big_endian_input(dtype: str) -> None:
    scalar = np.ones((), dtype)[()]  # a numpy scalar (np.generic), not an array
    assert_identical(np.asarray(scalar), from_tensor(to_tensor(scalar)))
    for empty in (np.zeros((0,), dtype), np.zeros((3, 0, 2), dtype)):
        assert_identical(empty, from_tensor(to_tensor(empty)))
    grid = np.arange(24).reshape(4, 6).astype(dtype)
    view = grid[::2, ::-3].T  # neither C- nor F-contiguous
    assert_identical(view, from_tensor(to_tensor(view)))
    swapped = grid.astype(np.dtype(dtype).newbyteorder(">"))
    out = from_tensor(to_tensor(swapped))
    assert out.dtype == np.dtype(dtype) and out.dtype.isnative
    np.testing.assert_array_equal(out, grid)


def test_decoded_array_owns_its_memory() -> None:
    proto = to_tensor(np.arange(4, dtype=np.float32))
    out = from_tensor(proto)
    out[0] = 99.0
    np.testing.assert_array_equal(from_tensor(proto), [0, 1, 2, 3])


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([1.0, 2.0], "must be a numpy array, got list"),
        (np.zeros(2, np.float16), "float16, which cannot cross the wire"),
        (np.zeros(2, np.complex64), "cannot cross the wire"),
        (np.array(["a"], object), "cannot cross the wire"),
    ],
)
def test_to_tensor_refuses_what_it_cannot_encode_exactly(value: object, message: str) -> None:
    with pytest.raises(WireError, match=message) as e:
        to_tensor(value, "chunks[0].rewards")  # type: ignore[arg-type]
    assert e.value.field == "chunks[0].rewards"


def raw(dtype: str, shape: list[int], data: bytes) -> replay_pb2.Tensor:
    return replay_pb2.Tensor(dtype=dtype, shape=shape, data=data)


@pytest.mark.parametrize(
    ("proto", "message"),
    [
        (raw("object", [1], b"\0" * 8), "has unsupported dtype 'object'"),
        (raw("<f4", [1], b"\0" * 4), "has unsupported dtype '<f4'"),
        (raw("", [], b""), "has unsupported dtype ''"),
        (raw("float32", [2, -1], b""), "negative dimension"),
        (raw("float32", [3], b"\0" * 11), "has 11 bytes of data, but float32 of shape [3] needs 12"),
        (raw("uint8", [2, 2], b"\0" * 5), "has 5 bytes of data"),
        (raw("bool", [3], b"\x00\x01\x07"), "is bool but holds bytes other than 0 and 1"),
    ],
)
def test_malformed_tensors_are_refused_without_a_spec(proto: replay_pb2.Tensor, message: str) -> None:
    with pytest.raises(WireError, match=message.replace("[", r"\[").replace("]", r"\]")) as e:
        from_tensor(proto, field="payload")
    assert str(e.value).startswith("payload ")


PIXELS = TensorSpec("chunks[0].obs[1] (pixels)", np.uint8, (84, 84, 3), leading=("T+1",))


def test_spec_mismatch_names_field_expected_and_actual() -> None:
    dims = {"T": 4}
    bad = to_tensor(np.zeros((5, 84, 84, 3), np.float32))
    with pytest.raises(WireError) as e:
        from_tensor(bad, PIXELS, dims)
    assert str(e.value) == (
        "chunks[0].obs[1] (pixels) is float32 of shape [5, 84, 84, 3], "
        "expected uint8 of shape [T+1, 84, 84, 3] with T = 4"
    )
    assert e.value.field == "chunks[0].obs[1] (pixels)"
    ok = from_tensor(to_tensor(np.zeros((5, 84, 84, 3), np.uint8)), PIXELS, dims)
    assert ok.shape == (5, 84, 84, 3)


@pytest.mark.parametrize(
    "array",
    [
        np.zeros((4, 84, 84, 3), np.uint8),  # T + 1 rows expected, T given
        np.zeros((5, 84, 84), np.uint8),  # rank
        np.zeros((5, 84, 3, 84), np.uint8),  # trailing shape
        np.zeros((5, 84, 84, 3), np.int64),  # dtype, no casting
    ],
)
def test_leading_dims_rank_trailing_shape_and_dtype_must_match(array: np.ndarray) -> None:
    with pytest.raises(WireError, match=r"\(pixels\) is .* expected uint8 of shape \[T\+1, 84, 84, 3\] with T = 4"):
        from_tensor(to_tensor(array), PIXELS, {"T": 4})


def test_leading_dims_are_bound_by_the_first_field_and_shared() -> None:
    dims: dict[str, int] = {}
    rewards = TensorSpec("rewards", np.float32, leading=("T",))
    actions = TensorSpec("actions", np.float32, (2,), leading=("T",))
    from_tensor(to_tensor(np.zeros(3, np.float32)), rewards, dims)
    assert dims == {"T": 3}
    with pytest.raises(WireError, match=r"actions is float32 of shape \[4, 2\], .* with T = 3"):
        from_tensor(to_tensor(np.zeros((4, 2), np.float32)), actions, dims)
    window = TensorSpec("mask", bool, leading=("B", "L"))
    dims = {"B": 2}
    from_tensor(to_tensor(np.zeros((2, 5), bool)), window, dims)
    assert dims == {"B": 2, "L": 5}
    same_symbol_twice = TensorSpec("square", np.float32, leading=("N", "N"))
    with pytest.raises(WireError, match="square"):
        from_tensor(to_tensor(np.zeros((2, 3), np.float32)), same_symbol_twice, {})


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_finite_and_sign_checks(bad: float) -> None:
    obs = TensorSpec("chunks[0].obs[0] (state)", np.float32, (3,), finite=True, leading=("T+1",))
    values = np.zeros((2, 3), np.float32)
    values[1, 2] = bad
    with pytest.raises(WireError, match=r"^chunks\[0\]\.obs\[0\] \(state\) has non-finite values$"):
        from_tensor(to_tensor(values), obs, {})
    loose = TensorSpec("free", np.float32, (3,), leading=("T+1",))
    assert not np.isfinite(from_tensor(to_tensor(values), loose, {})).all()  # allowed when not required
    priorities = TensorSpec("priorities", np.float64, finite=True, nonnegative=True, leading=("N",))
    with pytest.raises(WireError, match="priorities must be >= 0"):
        from_tensor(to_tensor(np.array([0.5, -1e-300])), priorities, {})
    np.testing.assert_array_equal(from_tensor(to_tensor(np.array([0.0, 2.0])), priorities, {}), [0, 2])


def test_a_spec_must_name_a_wire_dtype() -> None:
    with pytest.raises(ValueError, match="cannot cross the wire"):
        TensorSpec("x", np.float16)

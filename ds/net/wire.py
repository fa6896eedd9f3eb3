"""numpy arrays <-> ``asac.Tensor`` protos (dtype name, shape, raw bytes), checked against specs.

Nothing received is unpickled: an array travels as its numpy dtype name, its shape and its C-order
little-endian bytes, and is rebuilt with ``np.frombuffer`` after every property the receiver relies
on has been checked. Usage, on the two ends of a message::

    msg.rewards.CopyFrom(to_tensor(chunk.rewards))                   # sender
    dims: dict[str, int] = {}                                        # receiver: one per message
    rewards = from_tensor(msg.rewards, TensorSpec("rewards", np.float32, leading=("T",), finite=True), dims)
    obs = from_tensor(msg.obs[0], TensorSpec("obs[0] (state)", np.float32, (3,), leading=("T+1",)), dims)

``dims`` binds the symbolic leading dimensions (``T``, ``B``, ``L``, ``N``; ``T+1`` is one more
than ``T``) the first time they are seen, so that every field of a message must agree with the
first: a chunk whose observations do not have one row more than its rewards is refused. Every
violation is a :class:`WireError` naming the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from protos import replay_pb2

# The dtypes that may cross the wire. Anything else (object arrays, strings, structured dtypes)
# is refused on both ends: a receiver never interprets bytes as a type it did not ask for.
WIRE_DTYPES = frozenset({"bool", "uint8", "int32", "int64", "uint64", "float32", "float64"})
# Decoding runs per received tensor on the servers' hot paths: look dtypes up rather than build them
# (``np.dtype(name)`` and ``dtype.name`` cost microseconds each).
_WIRE_DTYPE = {name: np.dtype(name) for name in WIRE_DTYPES}
_LITTLE_ENDIAN = {name: dtype.newbyteorder("<") for name, dtype in _WIRE_DTYPE.items()}


class WireError(ValueError):
    """A tensor or message does not match what the receiver expects. ``field`` names where and
    ``reason`` continues the sentence: ``WireError("chunks[0].rewards", "has non-finite values")``
    reads "chunks[0].rewards has non-finite values"."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field} {reason}")
        self.field = field
        self.reason = reason


@dataclass(frozen=True)
class TensorSpec:
    """What a received tensor must be.

    Args:
        name: the field, as error messages name it (``"chunks[0].obs[1] (pixels)"``).
        dtype: required numpy dtype, exactly (no casting: a float64 image is an error).
        shape_suffix: the trailing dimensions, exactly.
        finite: floats must be finite (no NaN or inf).
        leading: symbolic leading dimensions (``("T",)``, ``("B", "L+1")``), bound through ``dims``.
        nonnegative: values must be ``>= 0`` (priorities).
    """

    name: str
    dtype: np.dtype
    shape_suffix: tuple[int, ...] = ()
    finite: bool = False
    leading: tuple[str, ...] = ()
    nonnegative: bool = False
    _dtype_name: str = field(init=False, repr=False, compare=False)
    _symbols: tuple[tuple[str, int], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "dtype", np.dtype(self.dtype))
        object.__setattr__(self, "shape_suffix", tuple(int(d) for d in self.shape_suffix))
        if self.dtype.name not in WIRE_DTYPES:
            raise ValueError(f"TensorSpec {self.name!r}: dtype {self.dtype} cannot cross the wire")
        object.__setattr__(self, "_dtype_name", self.dtype.name)
        object.__setattr__(self, "_symbols", tuple(_parse_symbol(s) for s in self.leading))

    def pattern(self) -> str:
        """The expected shape as text, e.g. ``[T+1, 84, 84, 3]``."""
        return "[" + ", ".join([*self.leading, *map(str, self.shape_suffix)]) + "]"


def to_tensor(array: np.ndarray | np.generic, field: str = "tensor") -> replay_pb2.Tensor:
    """Encode a numpy array (or scalar) as a Tensor proto: dtype name, shape, C-order LE bytes.

    Raises :class:`WireError` if it is not a numpy array or its dtype cannot cross the wire (a
    Python list would silently become float64 or int64, so it is refused rather than guessed).
    """
    if not isinstance(array, np.ndarray | np.generic):
        raise WireError(field, f"must be a numpy array, got {type(array).__name__}")
    dtype = array.dtype
    if dtype.name not in WIRE_DTYPES:
        raise WireError(
            field, f"has dtype {dtype}, which cannot cross the wire (allowed: {', '.join(sorted(WIRE_DTYPES))})"
        )
    little = np.asarray(array).astype(dtype.newbyteorder("<"), copy=False)  # a no-op on x86/ARM
    return replay_pb2.Tensor(dtype=dtype.name, shape=array.shape, data=little.tobytes(order="C"))


def from_tensor(
    proto: replay_pb2.Tensor,
    expected: TensorSpec | None = None,
    dims: dict[str, int] | None = None,
    field: str = "tensor",
) -> np.ndarray:
    """Decode a Tensor proto into a new, writable numpy array, checking it against ``expected``.

    Always checked: the dtype is a wire dtype, dimensions are >= 0, the byte length is exactly
    ``prod(shape) * itemsize``, bools are 0 or 1. With ``expected``: dtype, trailing shape and the
    leading dimensions (bound in ``dims``, which is updated), finiteness and sign. Any violation
    raises :class:`WireError` naming ``expected.name`` (or ``field``).
    """
    name = expected.name if expected is not None else field
    shape = tuple(proto.shape)
    dtype = _WIRE_DTYPE.get(proto.dtype)
    if dtype is None:
        raise WireError(name, f"has unsupported dtype {proto.dtype!r} (allowed: {', '.join(sorted(WIRE_DTYPES))})")
    if any(d < 0 for d in shape):
        raise WireError(name, f"has a negative dimension in its shape {list(shape)}")
    if expected is not None:
        _check_layout(expected, proto.dtype, shape, {} if dims is None else dims)
    nbytes = math.prod(shape) * dtype.itemsize
    if len(proto.data) != nbytes:
        raise WireError(name, f"has {len(proto.data)} bytes of data, but {_got(proto.dtype, shape)} needs {nbytes}")
    if dtype == np.bool_ and np.frombuffer(proto.data, dtype=np.uint8).max(initial=0) > 1:
        raise WireError(name, "is bool but holds bytes other than 0 and 1")
    array = np.frombuffer(proto.data, dtype=_LITTLE_ENDIAN[proto.dtype]).reshape(shape).astype(dtype, copy=True)
    if expected is not None and dtype.kind == "f":
        if expected.finite and not np.isfinite(array).all():
            raise WireError(name, "has non-finite values")
        if expected.nonnegative and (array < 0).any():
            raise WireError(name, "must be >= 0")
    return array


def _got(dtype: str, shape: tuple[int, ...]) -> str:
    return f"{dtype or '<no dtype>'} of shape {list(shape)}"


def _check_layout(spec: TensorSpec, dtype: str, shape: tuple[int, ...], dims: dict[str, int]) -> None:
    """Dtype, rank, trailing shape and leading dimensions; binds new leading symbols in ``dims``."""
    n_lead = len(spec.leading)
    ok = dtype == spec._dtype_name and len(shape) == n_lead + len(spec.shape_suffix)
    ok = ok and shape[n_lead:] == spec.shape_suffix
    new: dict[str, int] = {}
    if ok:
        for (base, offset), size in zip(spec._symbols, shape[:n_lead], strict=True):
            value = size - offset
            known = dims.get(base, new.get(base))
            if value < 0 or (known is not None and known != value):
                ok = False
                break
            new[base] = value
    if not ok:  # the message is built only here: decoding is on the servers' hot path
        bound = _bound_symbols(spec, dims)
        expected = f"{spec._dtype_name} of shape {spec.pattern()}{bound}"
        raise WireError(spec.name, f"is {_got(dtype, shape)}, expected {expected}")
    dims.update(new)


def _parse_symbol(symbol: str) -> tuple[str, int]:
    base, _, offset = symbol.partition("+")
    return base, int(offset or 0)


def _bound_symbols(spec: TensorSpec, dims: dict[str, int]) -> str:
    names = dict.fromkeys(_parse_symbol(s)[0] for s in spec.leading)
    known = [f"{n} = {dims[n]}" for n in names if n in dims]
    return f" with {', '.join(known)}" if known else ""

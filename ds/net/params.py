"""Parameter broadcast: the learner publishes each version once over ZeroMQ PUB; actors keep the newest.

Usage::

    # learner: one serialisation per version, whatever the number of actors; one StreamKey per start
    publisher = ParamsPublisher("tcp://0.0.0.0:5555", token=token, stream=StreamKey.fresh())
    publisher.publish(update, sac.acting_state_dict())           # every N updates; never blocks
    publisher.republish()                                         # now and then while no new version comes

    # actor: connect before or after the learner binds (ZeroMQ reconnects on its own); the stream key
    # is the one of the learner it registered with (RegisterActorReply: learner_id, params_key)
    stream = StreamKey(registration.learner_id, registration.params_key)
    subscriber = ParamsSubscriber(learner_address, params_spec(sac.acting_state_dict()), token=token, stream=stream)
    version, params = subscriber.wait(timeout_s=60)               # the first weights
    sac.load_acting_state_dict({k: torch.from_numpy(v) for k, v in params.items()})
    while acting:
        if (newer := subscriber.latest()) is not None:            # never blocks
            version, params = newer
            ...

**Wire format** (never pickle): one multipart message per version, ``[header, tensor_0, ..., tensor_n-1]``
plus ``[mac]`` when the message is signed (a stream key or a token). The header is UTF-8 JSON
``{"format": FORMAT, "version": int, "tensors": [{"name", "dtype", "shape", "nbytes"}, ...]}`` listing
the tensor frames in order; each tensor frame is the tensor's raw C-order little-endian bytes.
:func:`decode_params` checks every field, every frame length, the names/dtypes/shapes against the
registered spec and that floats are finite, and raises :class:`ParamsError` naming the tensor and the
problem; nothing unchecked reaches the weights.

**Latest-only.** ZeroMQ's ``ZMQ_CONFLATE`` keeps one message per queue but does not support multipart
messages, so both ends keep short queues instead. The publisher's PUB socket has ``SNDHWM=2``: for a
subscriber whose queue is full (a slow or stalled actor) PUB drops the message for that subscriber
only, so the learner never waits for anybody and its memory stays bounded. ZeroMQ delivers multipart
messages atomically, so a subscriber gets a whole version or none of it. The subscriber's SUB socket has
``RCVHWM=2``; :meth:`ParamsSubscriber.latest` drains everything queued and returns only the highest
valid version, newer than any it returned before; the rest are counted and dropped.

PUB drops the *new* message when a queue is full, not the queued ones: after a burst of publishes a
subscriber can sit a few versions behind until the next publish. A learner that keeps training publishes
again soon; one that goes quiet calls :meth:`ParamsPublisher.republish` now and then, which re-sends the
frames it already has (no serialisation) and also reaches subscribers that joined late. Without it a
late joiner gets the next published version (``GetParams`` in the learner service is the fallback).

**Signed frames.** The publisher appends an HMAC-SHA256 over the length-prefixed header and tensor
frames (one per token when the run's token file holds several while a token is rotated, in one frame of
``32 x n`` bytes, n <= MAX_MACS; ds/net/credentials.py); the subscriber verifies it (any of them under
any of its own tokens) (:func:`hmac.compare_digest`) before it parses anything, whatever
the version says, and counts messages that fail. The learner's stream (and ``GetParams``, the same
frames) is signed under its :class:`StreamKey`: a fresh random secret per learner start, handed to
each actor in its ``RegisterActorReply``, bound to the learner's id and, when the run has a token,
to the token too (:meth:`StreamKey.mac_key`). So an actor takes parameters only from the learner it
registered with: a process that takes the port of a learner that died, or a restarted learner before
the actor registers again, is refused, however high its versions. With a token, forging still needs
the token (a copy of the secret sniffed off plaintext gRPC is not enough). Without a stream key a
``token`` alone signs (the evolver's weight frames). A replayed old message is ignored by a subscriber
that has seen a newer version. Signing authenticates; it does not encrypt (use CURVE or a private
network for that).

One thread per publisher/subscriber: ZeroMQ sockets are not thread-safe.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import sys
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import zmq

from ds.net.credentials import Keyring, token_keys
from ds.net.stream_key import StreamKey

if TYPE_CHECKING:
    from torch import Tensor

FORMAT = "asac.params/1"
MAC_BYTES = hashlib.sha256().digest_size
MAX_MACS = 4
"""At most this many MACs in a message's MAC frame (one per token of the signer's token file)."""
Token = bytes | Keyring | None
"""The run's token: a keyring (read again when its file changes), one token, or None (unsigned)."""
# What may travel: plain numeric dtypes, no object/structured/string dtypes (and no bfloat16, which
# numpy lacks).
DTYPES = frozenset(
    ["bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float16", "float32", "float64"]
)
_HEADER_FIELDS = frozenset(["format", "version", "tensors"])
_ENTRY_FIELDS = frozenset(["name", "dtype", "shape", "nbytes"])
_KEEP = 4  # valid-looking messages kept per drain, highest versions first: bounds memory
_DRAIN_LIMIT = 1000  # messages read per latest() call: ends the drain under a fast flood

Params = Mapping[str, "Tensor | np.ndarray"]
ParamsSpec = Mapping[str, tuple[Any, Sequence[int]]]
"""Name -> (dtype, shape); dtype is anything ``np.dtype`` accepts or a ``torch.dtype``."""


def _notice_dead_links(socket: zmq.Socket) -> None:
    """TCP keepalive on ``socket`` (probes after 10 s of silence, every 5 s, the connection dropped after 2
    unanswered) and a connect that gives up after 2 s: across a partition a TCP connection otherwise
    looks alive until TCP's next retransmission, tens of seconds after the heal, and weights would not
    reach an actor meanwhile (it still fetches them when it registers again). Not ZeroMQ's own
    heartbeats (ZMQ_HEARTBEAT_IVL): with a subscriber's small receive queue they crash libzmq 4.3
    (``Assertion failed: _input_stopped``, zeromq/libzmq#3937; seen here in an actor after a heal)."""
    socket.setsockopt(zmq.TCP_KEEPALIVE, 1)
    socket.setsockopt(zmq.TCP_KEEPALIVE_IDLE, 10)
    socket.setsockopt(zmq.TCP_KEEPALIVE_INTVL, 5)
    socket.setsockopt(zmq.TCP_KEEPALIVE_CNT, 2)
    socket.setsockopt(zmq.CONNECT_TIMEOUT, 2_000)


class ParamsError(ValueError):
    """A parameter message that must not be applied; the text names the tensor (or header) and the problem."""


class _Signer(NamedTuple):
    """The MAC keys of a message (none: unsigned), one per token now, and who holds them, for error messages."""

    keys: tuple[bytes, ...]
    holder: str


def _signer(token: Token, stream: StreamKey | None) -> _Signer:
    tokens = token_keys(token)
    if stream is not None:
        keys = tuple(stream.mac_key(t) for t in tokens) or (stream.mac_key(None),)
        return _Signer(keys, f"learner {stream.learner_id}" + (" and the token" if tokens else ""))
    return _Signer(tokens, "the token")


def _sign(keys: tuple[bytes, ...], frames: Sequence[bytes]) -> bytes:
    """The MAC frame: one MAC per key (a token file with two tokens while one is rotated signs under
    both, so that a subscriber holding either takes it; ds/net/credentials.py)."""
    return b"".join(_mac(key, frames) for key in keys)


class _Entry(NamedTuple):
    name: str
    dtype: np.dtype
    shape: tuple[int, ...]
    nbytes: int


class _Message(NamedTuple):
    version: int
    entries: list[_Entry]
    blobs: Sequence[bytes]


# -- encoding --------------------------------------------------------------------------------------
def params_spec(state_dict: Params) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """The spec a subscriber checks messages against, from the state dict the publisher will send
    (e.g. ``sac.acting_state_dict()`` of a model built from the same config)."""
    return _normalise_spec({name: (value.dtype, value.shape) for name, value in state_dict.items()})


def encode_params(version: int, params: Params, token: Token = None, *, stream: StreamKey | None = None) -> list[bytes]:
    """Frames for one version: the JSON header, one raw little-endian frame per tensor, and an
    HMAC-SHA256 frame when ``stream`` or ``token`` is set (the stream's key when there is one, else the
    token). Tensors are copied (CPU, C order), so the caller may keep updating its weights while ZeroMQ
    sends the frames. Unsupported dtypes raise :class:`ParamsError`."""
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise ValueError(f"version must be a non-negative int, got {version!r}")
    entries, blobs = [], []
    for name, value in params.items():
        if not isinstance(name, str):
            raise ParamsError(f"{name!r}: tensor names must be str")
        array = _as_array(name, value)
        blobs.append(array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes())
        entries.append(_Entry(name, array.dtype, tuple(array.shape), len(blobs[-1])))
    frames = [_header(version, entries), *blobs]
    if keys := _signer(token, stream).keys:
        frames.append(_sign(keys, frames))
    return frames


def _torch() -> Any:
    """torch if this process has imported it, else None: only then can a value be a tensor or a dtype
    a torch one. The evolver, which relays weights as numpy arrays, never imports it."""
    return sys.modules.get("torch")


def _as_array(name: str, value: Tensor | np.ndarray) -> np.ndarray:
    if (torch := _torch()) is not None and isinstance(value, torch.Tensor):
        tensor = value.detach().cpu()
        try:
            value = tensor.numpy()
        except TypeError:
            raise ParamsError(f"{name}: dtype {tensor.dtype} cannot travel (allowed: {sorted(DTYPES)})") from None
    array = np.asarray(value)
    if array.dtype.name not in DTYPES:
        raise ParamsError(f"{name}: dtype {array.dtype} cannot travel (allowed: {sorted(DTYPES)})")
    return array


def _header(version: int, entries: Sequence[_Entry]) -> bytes:
    tensors = [{"name": e.name, "dtype": e.dtype.name, "shape": list(e.shape), "nbytes": e.nbytes} for e in entries]
    return json.dumps({"format": FORMAT, "version": version, "tensors": tensors}, separators=(",", ":")).encode()


def _mac(token: bytes, frames: Sequence[bytes]) -> bytes:
    # Each frame is length-prefixed so that moving bytes across a frame boundary changes the MAC.
    mac = hmac.new(token, digestmod=hashlib.sha256)
    for frame in frames:
        mac.update(len(frame).to_bytes(8, "little"))
        mac.update(frame)
    return mac.digest()


# -- decoding --------------------------------------------------------------------------------------
def decode_params(
    frames: Sequence[bytes],
    expected: ParamsSpec | None = None,
    token: Token = None,
    *,
    stream: StreamKey | None = None,
) -> tuple[int, dict[str, np.ndarray]]:
    """``(version, name -> array)`` from the frames of one message, or :class:`ParamsError`.

    Checked, in order: the MAC when ``stream`` or ``token`` is set (a missing or wrong one fails), the header (JSON
    object, format tag, version, well-formed tensor entries, unique names, allowed dtypes, ``nbytes ==
    prod(shape) * itemsize``), one frame per entry with exactly ``nbytes`` bytes, names equal to
    ``expected``'s with its dtypes and shapes, bools 0/1 and floats finite. Arrays are native-order,
    writable copies that do not keep the frames alive."""
    message = _read_message(frames, _signer(token, stream))
    spec = None if expected is None else _normalise_spec(expected)
    return message.version, _read_tensors(message, spec)


def _read_message(frames: Sequence[bytes], signer: _Signer) -> _Message:
    """The MAC, header and frame lengths: everything but the tensor values (cheap)."""
    if signer.keys:
        signature = frames[-1] if len(frames) >= 2 else b""
        if not signature or len(signature) % MAC_BYTES or len(signature) > MAX_MACS * MAC_BYTES:
            raise ParamsError(f"message: no MAC frame, but messages must be signed by {signer.holder} "
                              "(a publisher without the key?)")  # fmt: skip
        macs = [signature[i : i + MAC_BYTES] for i in range(0, len(signature), MAC_BYTES)]
        mine = [_mac(key, frames[:-1]) for key in signer.keys]
        if not any(hmac.compare_digest(mac, want) for mac in macs for want in mine):
            raise ParamsError(f"message: MAC does not verify: not signed by {signer.holder} (another publisher on "
                              "its port, a wrong token, or altered frames)")  # fmt: skip
        frames = frames[:-1]
    if not frames:
        raise ParamsError("message: no frames")
    try:
        header = json.loads(frames[0])
    except (ValueError, RecursionError) as e:
        raise ParamsError(f"header: not valid JSON ({e})") from None
    if not isinstance(header, dict):
        raise ParamsError(f"header: expected a JSON object, got {type(header).__name__}")
    if missing := _HEADER_FIELDS - header.keys():
        raise ParamsError(f"header: missing fields {sorted(missing)}")
    if header["format"] != FORMAT:
        raise ParamsError(f"header: format {header['format']!r}, expected {FORMAT!r}")
    version = header["version"]
    if not _is_count(version):
        raise ParamsError(f"header: version must be a non-negative int, got {version!r}")
    if not isinstance(header["tensors"], list):
        raise ParamsError("header: 'tensors' must be a list")
    entries = [_read_entry(i, entry) for i, entry in enumerate(header["tensors"])]
    names = [e.name for e in entries]
    if len(set(names)) != len(names):
        raise ParamsError(f"header: duplicate tensor names {sorted({n for n in names if names.count(n) > 1})}")
    if len(frames) != 1 + len(entries):
        signed = not signer.keys and len(frames) == 2 + len(entries)
        hint = " (a trailing MAC? this subscriber has no token)" if signed else ""
        raise ParamsError(f"message: {len(frames)} frames, expected 1 header + {len(entries)} tensor frames{hint}")
    for entry, frame in zip(entries, frames[1:], strict=True):
        if len(frame) != entry.nbytes:
            raise ParamsError(f"{entry.name}: frame has {len(frame)} bytes, header says {entry.nbytes}")
    return _Message(version, entries, frames[1:])


def _read_entry(index: int, entry: Any) -> _Entry:
    if not isinstance(entry, dict) or entry.keys() != _ENTRY_FIELDS:
        raise ParamsError(f"header: tensor entry {index} must have exactly the fields {sorted(_ENTRY_FIELDS)}")
    name, dtype, shape, nbytes = entry["name"], entry["dtype"], entry["shape"], entry["nbytes"]
    if not isinstance(name, str):
        raise ParamsError(f"header: tensor entry {index} has a non-string name {name!r}")
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise ParamsError(f"{name}: dtype {dtype!r} is not allowed (allowed: {sorted(DTYPES)})")
    if not isinstance(shape, list) or not all(_is_count(d) for d in shape):
        raise ParamsError(f"{name}: shape must be a list of non-negative ints, got {shape!r}")
    if not _is_count(nbytes):
        raise ParamsError(f"{name}: nbytes must be a non-negative int, got {nbytes!r}")
    needed = math.prod(shape) * np.dtype(dtype).itemsize
    if nbytes != needed:
        raise ParamsError(f"{name}: header says {nbytes} bytes, but {dtype} {shape} needs {needed}")
    return _Entry(name, np.dtype(dtype), tuple(shape), nbytes)


def _read_tensors(message: _Message, spec: dict[str, tuple[np.dtype, tuple[int, ...]]] | None) -> dict[str, np.ndarray]:
    """The tensor values of a message whose header :func:`_read_message` checked."""
    if spec is not None:
        names = {e.name for e in message.entries}
        if missing := spec.keys() - names:
            raise ParamsError(f"missing tensors: {', '.join(sorted(missing))}")
        if unexpected := names - spec.keys():
            raise ParamsError(f"unexpected tensors: {', '.join(sorted(unexpected))}")
        for e in message.entries:
            dtype, shape = spec[e.name]
            if (e.dtype, e.shape) != (dtype, shape):
                raise ParamsError(f"{e.name}: expected {dtype} {list(shape)}, got {e.dtype} {list(e.shape)}")
    params = {}
    for e, blob in zip(message.entries, message.blobs, strict=True):
        if e.dtype.kind == "b" and np.frombuffer(blob, np.uint8).max(initial=0) > 1:
            raise ParamsError(f"{e.name}: bool bytes other than 0 and 1")
        array = np.frombuffer(blob, e.dtype.newbyteorder("<")).astype(e.dtype).reshape(e.shape)
        if e.dtype.kind == "f":
            bad = ~np.isfinite(array)
            if bad.any():
                first = tuple(int(i) for i in np.unravel_index(int(np.argmax(bad)), e.shape))
                raise ParamsError(f"{e.name}: {int(bad.sum())} non-finite values (first at index {first})")
        params[e.name] = array
    return params


def _normalise_spec(spec: ParamsSpec) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """Native-order numpy dtypes and int tuples; a dtype that cannot travel raises :class:`ParamsError`."""
    out = {}
    for name, (dtype, shape) in spec.items():
        torch = _torch()
        is_torch = torch is not None and isinstance(dtype, torch.dtype)
        empty = torch.empty(0, dtype=dtype) if is_torch else np.empty(0, dtype)
        out[name] = (np.dtype(_as_array(name, empty).dtype.name), tuple(int(d) for d in shape))
    return out


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


# -- sockets ---------------------------------------------------------------------------------------
class ParamsPublisher:
    """The learner's end: binds a PUB socket and sends each version to every connected subscriber.

    ``address`` is a ZeroMQ endpoint to bind (``tcp://127.0.0.1:*`` picks a free port; the bound one is
    :attr:`address`). :meth:`publish` never blocks on slow subscribers (see the module docstring).
    ``stream`` (the learner's :class:`StreamKey`, with ``token`` when the run has one) signs every message."""

    def __init__(
        self,
        address: str,
        *,
        token: Token = None,
        stream: StreamKey | None = None,
        sndhwm: int = 2,
        context: zmq.Context | None = None,
    ) -> None:
        token_keys(token)  # a bad token fails here, not at the first publish
        self._token = token
        self.stream = stream
        self._socket = (context or zmq.Context.instance()).socket(zmq.PUB)
        self._socket.setsockopt(zmq.LINGER, 0)  # close() must not wait for subscribers that stopped reading
        self._socket.setsockopt(zmq.SNDHWM, sndhwm)
        _notice_dead_links(self._socket)
        self._socket.bind(address)
        self.address: str = self._socket.getsockopt_string(zmq.LAST_ENDPOINT)
        self.version: int | None = None
        self.published = 0
        self.republished = 0
        self.bytes_sent = 0
        self.publish_seconds = 0.0  # in publish(): copying, signing and sending, over all publishes
        self.mac_seconds = 0.0  # of which signing (HMAC-SHA256 over the frames)
        self._frames: list[bytes] | None = None

    def publish(self, version: int, params: Params) -> int:
        """Serialise ``params`` once and send it as ``version`` (which must increase); returns the bytes
        of one copy of the message."""
        if self.version is not None and version <= self.version:
            raise ValueError(f"version {version} after {self.version}: subscribers ignore versions that do not grow")
        started = time.perf_counter()
        frames = encode_params(version, params)
        if keys := _signer(self._token, self.stream).keys:
            signing = time.perf_counter()
            frames.append(_sign(keys, frames))
            self.mac_seconds += time.perf_counter() - signing
        self._send(frames)
        self.version, self._frames = version, frames
        self.published += 1
        self.publish_seconds += time.perf_counter() - started
        return sum(len(f) for f in frames)

    @property
    def frames(self) -> list[bytes] | None:
        """The frames of the last published version (None before the first): what the learner's
        ``GetParams`` hands to late joiners, so that a version is still serialised only once."""
        return self._frames

    def republish(self) -> bool:
        """Send the last published version again, from the frames already built; False if none yet.
        Subscribers that already have it skip it; ones that missed it (full queue, late join) get it."""
        if self._frames is None:
            return False
        self._send(self._frames)
        self.republished += 1
        return True

    def _send(self, frames: list[bytes]) -> None:
        # copy=False: ZeroMQ references the immutable bytes and shares one message between all
        # subscribers. PUB never blocks (a full subscriber queue drops the message for that subscriber);
        # NOBLOCK states it at the call.
        self._socket.send_multipart(frames, flags=zmq.NOBLOCK, copy=False)
        self.bytes_sent += sum(len(f) for f in frames)

    def metrics(self) -> dict[str, float]:
        """Counters for the learner's metrics dict (the caller adds its role prefix)."""
        return {
            "params/version": -1 if self.version is None else self.version,
            "params/published": self.published,
            "params/republished": self.republished,
            "params/bytes_sent": self.bytes_sent,
            "params/publish_ms": 1e3 * self.publish_seconds / max(self.published, 1),
            "params/mac_ms": 1e3 * self.mac_seconds / max(self.published, 1),
        }

    def close(self) -> None:
        self._socket.close(linger=0)

    def __enter__(self) -> ParamsPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ParamsSubscriber:
    """The actor's end: a SUB socket connected to a publisher, returning only the newest valid version.

    Every message is checked against ``expected`` (see :func:`decode_params`). ``MAXMSGSIZE`` is left
    unset on purpose: ZeroMQ treats an oversized frame as a protocol error and drops the connection for
    good (no reconnect), where a counted rejection naming the tensor is what an operator needs. With
    ``stream`` (the key of the learner this actor registered with) only that learner's messages are
    taken, whatever their version; anything else is counted as rejected. Counters:
    ``received`` = ``accepted`` + ``rejected`` (invalid; ``last_error`` says why) + ``skipped`` (not
    newer than what was returned, or superseded in the same drain)."""

    def __init__(
        self,
        address: str,
        expected: ParamsSpec,
        *,
        token: Token = None,
        stream: StreamKey | None = None,
        rcvhwm: int = 2,
        context: zmq.Context | None = None,
    ) -> None:
        self.address = address
        self._spec = _normalise_spec(expected)
        token_keys(token)
        self._token, self._stream = token, stream
        self._socket = (context or zmq.Context.instance()).socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.RCVHWM, rcvhwm)
        self._socket.setsockopt(zmq.SUBSCRIBE, b"")
        _notice_dead_links(self._socket)
        self._socket.connect(address)  # works before the publisher binds; ZeroMQ retries until it does
        self.version: int | None = None
        self.received = self.accepted = self.rejected = self.skipped = 0
        self.last_error: str | None = None

    def latest(self, timeout_ms: int = 0) -> tuple[int, dict[str, np.ndarray]] | None:
        """The highest valid version queued that is newer than the last one returned, or None.
        Waits up to ``timeout_ms`` for a first message, then reads everything queued without blocking."""
        if timeout_ms > 0 and not self._socket.poll(timeout_ms):
            return None
        candidates: list[_Message] = []
        for _ in range(_DRAIN_LIMIT):
            try:
                frames = self._socket.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            self.received += 1
            try:
                message = _read_message(frames, _signer(self._token, self._stream))
            except ParamsError as e:
                self._reject(e)
                continue
            if self.version is not None and message.version <= self.version:
                self.skipped += 1
                continue
            candidates.append(message)
            if len(candidates) > _KEEP:
                candidates.remove(min(candidates, key=lambda m: m.version))
                self.skipped += 1
        candidates.sort(key=lambda m: m.version, reverse=True)
        for i, message in enumerate(candidates):
            try:
                params = _read_tensors(message, self._spec)
            except ParamsError as e:
                self._reject(e)
                continue
            self.skipped += len(candidates) - i - 1
            self.version = message.version
            self.accepted += 1
            return message.version, params
        return None

    def wait(self, timeout_s: float) -> tuple[int, dict[str, np.ndarray]]:
        """Block until a version newer than the last returned arrives (the first one, for an actor
        starting up); :class:`TimeoutError` after ``timeout_s`` seconds, saying what was rejected."""
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            got = self.latest(timeout_ms=max(1, math.ceil(remaining * 1000)))
            if got is not None:
                return got
        rejected = f"; {self.rejected} rejected, last: {self.last_error}" if self.rejected else ""
        raise TimeoutError(f"no parameters newer than {self.version} from {self.address} in {timeout_s} s{rejected}")

    def _reject(self, error: ParamsError) -> None:
        self.rejected += 1
        self.last_error = str(error)

    def metrics(self) -> dict[str, float]:
        """Counters for the actor's metrics dict (the caller adds its role prefix)."""
        return {
            "params/version": -1 if self.version is None else self.version,
            "params/received": self.received,
            "params/accepted": self.accepted,
            "params/rejected": self.rejected,
            "params/skipped": self.skipped,
        }

    def close(self) -> None:
        self._socket.close(linger=0)

    def __enter__(self) -> ParamsSubscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

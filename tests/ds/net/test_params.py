"""Parameter broadcast: the wire format round-trips and refuses every malformed message, and over real
loopback sockets subscribers end on the newest version, never go backwards, and never slow the publisher."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
import zmq
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import ds.net.params
from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from ds.net.params import (
    DTYPES,
    ParamsError,
    ParamsPublisher,
    ParamsSubscriber,
    decode_params,
    encode_params,
    params_spec,
)

TOKEN = b"shared secret"
SPEC = {"a": (np.float32, (2, 3)), "b": (np.int64, (5,))}


def small_params(version: int = 0) -> dict[str, np.ndarray]:
    return {"a": np.full((2, 3), version, np.float32), "b": np.arange(5, dtype=np.int64) + version}


def make_sac(seed: int) -> SAC:
    spec = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2))
    return SAC(spec, SacConfig(seed=seed), NNConfig(hidden_units=[16, 16]), ReplayConfig())


def until(condition: Callable[[], bool], action: Callable[[], object] = lambda: None, timeout_s: float = 10.0) -> None:
    """Repeat ``action`` until ``condition`` holds (a settle loop: no fixed sleeps, generous timeout)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the condition"
        action()


def reaches(sub: ParamsSubscriber, version: int) -> Callable[[], bool]:
    """A condition for :func:`until`: read what is queued; is ``sub`` now at ``version``?"""

    def check() -> bool:
        sub.latest(timeout_ms=20)
        return sub.version == version

    return check


def counts(sub: ParamsSubscriber, counter: str, value: int) -> Callable[[], bool]:
    """A condition for :func:`until`: read what is queued; has ``sub.<counter>`` reached ``value``?"""

    def check() -> bool:
        sub.latest(timeout_ms=20)
        return getattr(sub, counter) >= value

    return check


@pytest.fixture
def ctx() -> Iterator[zmq.Context]:
    context = zmq.Context()
    yield context
    context.destroy(linger=0)


# -- wire format -----------------------------------------------------------------------------------
def test_round_trip_of_a_sac_acting_state_dict() -> None:
    source, target = make_sac(seed=1), make_sac(seed=2)
    state = source.acting_state_dict()
    version, params = decode_params(encode_params(7, state), params_spec(target.acting_state_dict()))
    assert version == 7 and list(params) == list(state)
    target.load_acting_state_dict({k: torch.from_numpy(v) for k, v in params.items()})
    for name, tensor in target.acting_state_dict().items():
        assert torch.equal(tensor, state[name]), name


@pytest.mark.parametrize("dtype", sorted(DTYPES))
@pytest.mark.parametrize("shape", [(), (0,), (3,), (2, 0, 5), (2, 3, 4)])
def test_round_trip_of_every_dtype_and_shape(dtype: str, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(0)
    array = (rng.integers(0, 2, shape) if dtype == "bool" else rng.integers(0, 100, shape)).astype(dtype)
    version, params = decode_params(encode_params(3, {"x": array}, TOKEN), {"x": (dtype, shape)}, TOKEN)
    assert version == 3
    assert params["x"].dtype == np.dtype(dtype) and params["x"].shape == shape
    np.testing.assert_array_equal(params["x"], array)
    assert params["x"].flags.writeable


def test_torch_big_endian_and_strided_inputs_travel_as_their_values() -> None:
    base = np.arange(12, dtype=np.float64).reshape(3, 4)
    params: dict[str, torch.Tensor | np.ndarray] = {
        "big_endian": base.astype(">f4"),
        "transposed": base.T,
        "tensor": torch.arange(6, dtype=torch.float16).reshape(2, 3).t(),
        "flags": torch.tensor([True, False]),
        "grad": torch.ones(2, requires_grad=True),
    }
    _, out = decode_params(encode_params(0, params), params_spec(params))
    np.testing.assert_array_equal(out["big_endian"], base.astype(np.float32))
    np.testing.assert_array_equal(out["transposed"], base.T)
    np.testing.assert_array_equal(out["tensor"], np.arange(6, dtype=np.float16).reshape(2, 3).T)
    np.testing.assert_array_equal(out["flags"], [True, False])
    assert params_spec(params)["tensor"] == (np.dtype(np.float16), (3, 2))


@pytest.mark.parametrize(
    "value", [torch.zeros(2, dtype=torch.bfloat16), np.array(["x"]), np.array([object()]), np.zeros(2, np.complex64)]
)
def test_dtypes_that_cannot_travel_are_refused_when_encoding(value: object) -> None:
    with pytest.raises(ParamsError, match="w: dtype .* cannot travel"):
        encode_params(0, {"w": value})  # type: ignore[dict-item]


array_dicts = st.dictionaries(
    st.text(min_size=1, max_size=12),
    st.sampled_from(sorted(DTYPES)).flatmap(
        lambda dtype: (
            hnp.arrays(
                dtype,
                hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4),
                elements={"allow_nan": False, "allow_infinity": False},
            )
            if dtype.startswith("float")
            else hnp.arrays(dtype, hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4))
        )
    ),
    max_size=5,
)


@given(params=array_dicts, version=st.integers(0, 2**63), signed=st.booleans())
def test_random_dicts_round_trip(params: dict[str, np.ndarray], version: int, signed: bool) -> None:
    token = TOKEN if signed else None
    got_version, got = decode_params(encode_params(version, params, token), params_spec(params), token)
    assert got_version == version and got.keys() == params.keys()
    for name, array in params.items():
        assert got[name].dtype == array.dtype
        np.testing.assert_array_equal(got[name], array)


@given(frames=st.lists(st.binary(max_size=64), max_size=4), signed=st.booleans())
def test_arbitrary_frames_raise_params_error_and_nothing_else(frames: list[bytes], signed: bool) -> None:
    with pytest.raises(ParamsError):
        decode_params(frames, SPEC, TOKEN if signed else None)


@given(frame=st.integers(0, 3), position=st.integers(0, 10_000), flip=st.integers(1, 255))
def test_any_flipped_byte_fails_the_mac(frame: int, position: int, flip: int) -> None:
    frames = [bytearray(f) for f in encode_params(5, small_params(5), TOKEN)]
    frames[frame][position % len(frames[frame])] ^= flip
    with pytest.raises(ParamsError, match="MAC does not verify"):
        decode_params([bytes(f) for f in frames], SPEC, TOKEN)


@given(frame=st.integers(0, 2), cut=st.integers(1, 48))
def test_any_truncated_frame_is_refused(frame: int, cut: int) -> None:
    frames = encode_params(5, small_params(5))
    frames[frame] = frames[frame][: max(0, len(frames[frame]) - cut)]
    with pytest.raises(ParamsError):
        decode_params(frames, SPEC)


def edit_header(edit: Callable[[dict], object], frames: list[bytes] | None = None) -> list[bytes]:
    frames = frames or encode_params(1, small_params(1))
    header = json.loads(frames[0])
    edit(header)
    return [json.dumps(header).encode(), *frames[1:]]


def nan_params() -> list[bytes]:
    params = small_params(1)
    params["a"][1, 2] = np.nan
    return encode_params(1, params)


# (frames, token the receiver holds, a piece of the expected message)
MALFORMED: dict[str, tuple[Callable[[], list[bytes]], bytes | None, str]] = {
    "bad json": (lambda: [b"{not json", *encode_params(1, small_params())[1:]], None, "header: not valid JSON"),
    "not an object": (lambda: [b"[1, 2]", *encode_params(1, small_params())[1:]], None, "expected a JSON object"),
    "no frames": (lambda: [], None, "message: no frames"),
    "wrong format": (lambda: edit_header(lambda h: h.update(format="pickle")), None, "format 'pickle'"),
    "missing version": (lambda: edit_header(lambda h: h.pop("version")), None, "missing fields ['version']"),
    "negative version": (lambda: edit_header(lambda h: h.update(version=-1)), None, "version must be"),
    "bool version": (lambda: edit_header(lambda h: h.update(version=True)), None, "version must be"),
    "entry fields": (lambda: edit_header(lambda h: h["tensors"][0].pop("nbytes")), None, "tensor entry 0 must have"),
    "object dtype": (lambda: edit_header(lambda h: h["tensors"][0].update(dtype="object")), None, "a: dtype 'object'"),
    "bad shape": (lambda: edit_header(lambda h: h["tensors"][0].update(shape=[2, -3])), None, "a: shape must be"),
    "nbytes lie": (lambda: edit_header(lambda h: h["tensors"][0].update(nbytes=8)), None, "a: header says 8 bytes"),
    "duplicate": (lambda: edit_header(lambda h: h["tensors"][1].update(name="a")), None, "duplicate tensor names"),
    "missing tensor": (lambda: encode_params(1, {"a": small_params()["a"]}), None, "missing tensors: b"),
    "extra tensor": (lambda: encode_params(1, {**small_params(), "c": np.zeros(1)}), None, "unexpected tensors: c"),
    "wrong dtype": (
        lambda: encode_params(1, {**small_params(), "a": np.zeros((2, 3))}),
        None,
        "a: expected float32 [2, 3], got float64 [2, 3]",
    ),
    "wrong shape": (
        lambda: encode_params(1, {**small_params(), "a": np.zeros((3, 2), np.float32)}),
        None,
        "a: expected float32 [2, 3], got float32 [3, 2]",
    ),
    "truncated": (lambda: [*encode_params(1, small_params())[:2], b"\0" * 39], None, "b: frame has 39 bytes"),
    "missing frame": (lambda: encode_params(1, small_params())[:2], None, "2 frames, expected 1 header + 2"),
    "nan": (nan_params, None, "a: 1 non-finite values (first at index (1, 2))"),
    "bad bool": (
        lambda: [*encode_params(1, {"a": np.zeros((2, 3), np.float32), "f": np.zeros(2, bool)})[:2], b"\0\2"],
        None,
        "f: bool bytes other than 0 and 1",
    ),
    "wrong mac": (lambda: encode_params(1, small_params(), b"another secret"), TOKEN, "MAC does not verify"),
    "no mac": (lambda: encode_params(1, small_params()), TOKEN, "no MAC frame"),
    "unexpected mac": (lambda: encode_params(1, small_params(), TOKEN), None, "a trailing MAC?"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_messages_raise_naming_the_problem(case: str) -> None:
    make, token, problem = MALFORMED[case]
    spec = {"a": (np.float32, (2, 3)), "f": (np.bool_, (2,))} if case == "bad bool" else SPEC
    with pytest.raises(ParamsError) as error:
        decode_params(make(), spec, token)
    assert problem in str(error.value)


# -- sockets ---------------------------------------------------------------------------------------
def raw_pub(ctx: zmq.Context) -> tuple[zmq.Socket, str]:
    """A bare PUB socket: a peer that may send anything."""
    sock = ctx.socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    return sock, f"tcp://127.0.0.1:{port}"


def test_subscriber_rejects_each_malformed_message_and_still_accepts_the_next_valid_one(ctx: zmq.Context) -> None:
    pub, address = raw_pub(ctx)
    with ParamsSubscriber(address, SPEC, context=ctx) as sub:
        until(reaches(sub, 0), lambda: pub.send_multipart(encode_params(0, small_params(0))))
        unsigned = {n: make for n, (make, token, _) in MALFORMED.items() if token is None}
        del unsigned["no frames"], unsigned["bad bool"]  # ZeroMQ sends no empty message; another spec
        for i, (name, make) in enumerate(sorted(unsigned.items()), start=1):
            pub.send_multipart(make())
            until(counts(sub, "rejected", i))
            assert sub.last_error is not None and MALFORMED[name][2] in sub.last_error, name
            assert sub.version == 0
        pub.send_multipart(encode_params(1, small_params(1)))
        got = sub.latest(timeout_ms=5000)
        assert got is not None and got[0] == 1
        np.testing.assert_array_equal(got[1]["a"], np.ones((2, 3)))
        assert sub.received == sub.accepted + sub.rejected + sub.skipped
    pub.close()


def test_token_signed_stream(ctx: zmq.Context) -> None:
    with (
        ParamsPublisher("tcp://127.0.0.1:*", token=TOKEN, context=ctx) as pub,
        ParamsSubscriber(pub.address, SPEC, token=TOKEN, context=ctx) as good,
        ParamsSubscriber(pub.address, SPEC, token=b"wrong", context=ctx) as wrong,
        ParamsSubscriber(pub.address, SPEC, context=ctx) as unsigned,
    ):
        pub.publish(0, small_params(0))
        until(reaches(good, 0), pub.republish)
        until(counts(wrong, "rejected", 1), pub.republish)
        until(counts(unsigned, "rejected", 1), pub.republish)
        assert wrong.version is None and wrong.last_error is not None and "MAC does not verify" in wrong.last_error
        assert unsigned.version is None and unsigned.last_error is not None and "trailing MAC" in unsigned.last_error


def test_a_subscriber_with_the_token_drops_unsigned_and_forged_frames_and_keeps_its_weights(ctx: zmq.Context) -> None:
    """A peer without the run's token (or with another) at the publisher's address: every message it
    sends is dropped, the subscriber keeps the weights it has, and the next signed version gets through."""
    pub, address = raw_pub(ctx)
    with ParamsSubscriber(address, SPEC, token=TOKEN, context=ctx) as sub:
        until(reaches(sub, 0), lambda: pub.send_multipart(encode_params(0, small_params(0), TOKEN)))
        forged = [encode_params(5, small_params(5)), encode_params(6, small_params(6), b"a guess")]
        for i, frames in enumerate(forged, start=1):
            pub.send_multipart(frames)
            until(counts(sub, "rejected", i))
        assert sub.version == 0 and sub.last_error is not None and "MAC does not verify" in sub.last_error
        pub.send_multipart(encode_params(7, small_params(7), TOKEN))
        got = sub.latest(timeout_ms=5000)
        assert got is not None and got[0] == 7 and sub.rejected == 2
        np.testing.assert_array_equal(got[1]["b"], np.arange(5) + 7)
    pub.close()


def test_eight_subscribers_end_on_the_newest_version(ctx: zmq.Context, monkeypatch: pytest.MonkeyPatch) -> None:
    encodes: list[int] = []

    def counting_encode(version: int, *args: object, **kwargs: object) -> list[bytes]:
        encodes.append(version)
        return encode_params(version, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(ds.net.params, "encode_params", counting_encode)
    sac = make_sac(seed=0)
    spec = params_spec(sac.acting_state_dict())
    with ParamsPublisher("tcp://127.0.0.1:*", context=ctx) as pub:
        subs = [ParamsSubscriber(pub.address, spec, context=ctx) for _ in range(8)]
        seen: list[list[int]] = [[] for _ in subs]

        def poll_all() -> bool:
            for sub, versions in zip(subs, seen, strict=True):
                if (got := sub.latest(timeout_ms=5)) is not None:
                    versions.append(got[0])
            return all(v and v[-1] == pub.version for v in seen)

        state = sac.acting_state_dict()
        pub.publish(0, state)
        until(poll_all, pub.republish)
        for version in range(1, 11):  # quick publishes: a subscriber may skip any but the last
            pub.publish(version, {k: v + version for k, v in state.items()})
        until(poll_all, pub.republish)
        assert pub.published == 11 and encodes == list(range(11))  # one serialisation per version, 8 subscribers
        for sub, versions in zip(subs, seen, strict=True):
            assert versions[-1] == 10 and versions == sorted(set(versions))
            assert sub.accepted == len(versions) and sub.rejected == 0
            sub.close()


def test_a_subscriber_that_never_reads_does_not_block_the_publisher(ctx: zmq.Context) -> None:
    params = {"w": np.zeros(256 * 1024, np.float32)}  # 1 MiB
    spec = params_spec(params)
    with (
        ParamsPublisher("tcp://127.0.0.1:*", context=ctx) as pub,
        ParamsSubscriber(pub.address, spec, context=ctx) as fast,
        ParamsSubscriber(pub.address, spec, context=ctx) as slow,
    ):
        pub.publish(0, params)
        until(reaches(slow, 0), pub.republish)
        until(reaches(fast, 0), pub.republish)
        done = threading.Event()

        def burst() -> None:  # on a thread so a blocked send fails the test instead of hanging it
            for version in range(1, 201):
                params["w"][0] = version
                pub.publish(version, params)
            done.set()

        thread = threading.Thread(target=burst, daemon=True)
        thread.start()
        deadline = time.monotonic() + 60
        while not done.wait(0.005) and time.monotonic() < deadline:
            fast.latest()  # the fast subscriber keeps reading; the slow one never does
        assert done.is_set(), "publish blocked on a slow subscriber"
        thread.join()
        assert pub.published == 201 and pub.bytes_sent >= 201 * params["w"].nbytes
        until(reaches(fast, 200), pub.republish)  # a burst may leave it behind: republish is the remedy
        assert slow.received == 1  # everything else waits in bounded queues or was dropped by PUB
        while slow.latest(timeout_ms=200) is not None:
            pass
        assert slow.received < 100, "the slow subscriber's queue held most of the burst: PUB did not drop"
        assert slow.version is not None and slow.rejected == 0


def test_versions_never_go_backwards(ctx: zmq.Context) -> None:
    pub, address = raw_pub(ctx)
    with ParamsSubscriber(address, SPEC, context=ctx) as sub:
        until(reaches(sub, 2), lambda: pub.send_multipart(encode_params(2, small_params(2))))
        returned = [2]
        for version in [3, 1, 5, 4, 5, 9, 0, 6, 10]:  # one at a time
            pub.send_multipart(encode_params(version, small_params(version)))
            until(counts(sub, "received", sub.received + 1))
            if sub.version != returned[-1]:
                returned.append(version)
                assert sub.version == version
        assert returned == [2, 3, 5, 9, 10]
        got = []
        for version in [12, 20, 11, 15]:  # sent together: whatever is queued, the highest valid one wins
            pub.send_multipart(encode_params(version, small_params(version)))
        total = sub.received + 4
        while sub.received < total:
            if (newer := sub.latest(timeout_ms=100)) is not None:
                got.append(newer)
        assert [v for v, _ in got] == sorted({v for v, _ in got}) and got[-1][0] == sub.version == 20
        np.testing.assert_array_equal(got[-1][1]["b"], np.arange(5) + 20)
        assert sub.received == sub.accepted + sub.rejected + sub.skipped
    pub.close()


def test_any_start_order_and_wait(ctx: zmq.Context, tmp_path: Path) -> None:
    address = f"ipc://{tmp_path}/params"
    with ParamsSubscriber(address, SPEC, context=ctx) as sub:  # connects before anything is bound
        with pytest.raises(TimeoutError, match="no parameters newer than None"):
            sub.wait(timeout_s=0.05)
        stop = threading.Event()

        def learner() -> None:
            with ParamsPublisher(address, context=ctx) as pub:
                pub.publish(4, small_params(4))
                while not stop.wait(0.02):
                    pub.republish()

        thread = threading.Thread(target=learner, daemon=True)
        thread.start()
        try:
            version, params = sub.wait(timeout_s=10)
        finally:
            stop.set()
            thread.join()
        assert version == 4
        np.testing.assert_array_equal(params["b"], np.arange(5) + 4)


def test_an_oversized_message_is_rejected_naming_the_tensor(ctx: zmq.Context) -> None:
    pub, address = raw_pub(ctx)
    with ParamsSubscriber(address, SPEC, context=ctx) as sub:
        until(reaches(sub, 0), lambda: pub.send_multipart(encode_params(0, small_params(0))))
        huge: dict[str, np.ndarray] = {
            "a": np.zeros((2, 3), np.float32),
            "b": np.zeros(1 << 20, np.int64),
        }  # an 8 MiB frame
        pub.send_multipart(encode_params(1, huge))
        until(counts(sub, "rejected", 1))
        assert sub.last_error == "b: expected int64 [5], got int64 [1048576]"
        until(reaches(sub, 2), lambda: pub.send_multipart(encode_params(2, small_params(2))))
    pub.close()


def test_publisher_counts_and_refuses_versions_that_do_not_grow(ctx: zmq.Context) -> None:
    with ParamsPublisher("tcp://127.0.0.1:*", context=ctx) as pub:
        assert pub.address.startswith("tcp://127.0.0.1:") and not pub.republish()
        size = pub.publish(3, small_params(3))
        assert size == sum(len(f) for f in encode_params(3, small_params(3)))
        with pytest.raises(ValueError, match="version 3 after 3"):
            pub.publish(3, small_params(3))
        assert pub.republish()
        metrics = pub.metrics()
        assert {k: metrics.pop(k) for k in ("params/publish_ms", "params/mac_ms")} == {
            "params/publish_ms": pytest.approx(1e3 * pub.publish_seconds),
            "params/mac_ms": 0.0,  # no token, no stream: nothing signed
        }
        assert metrics == {
            "params/version": 3,
            "params/published": 1,
            "params/republished": 1,
            "params/bytes_sent": 2 * size,
        }
    with ParamsPublisher("tcp://127.0.0.1:*", token=b"k" * 32, context=ctx) as signed:
        signed.publish(1, small_params(3))
        assert 0 < signed.mac_seconds <= signed.publish_seconds  # the MAC's cost is measured per publish

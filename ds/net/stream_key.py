"""Who may send an actor parameters: :class:`StreamKey`, one learner start's id and random secret.

The learner draws one at start (:meth:`StreamKey.fresh`), signs every parameter message with
:meth:`StreamKey.mac_key` (ds/net/params.py) and hands the secret to each actor in its
``RegisterActorReply.params_key`` (protos/learner.proto); an actor verifies what it receives under the
key of the learner it registered with, so a process that takes a dead learner's port, or a learner
that restarted before the actor registered again, is refused whatever version it claims
(docs/security.md section 2).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import uuid
from dataclasses import dataclass, field

STREAM_SECRET_BYTES = 32
_STREAM_LABEL = b"asac params stream/1"


@dataclass(frozen=True)
class StreamKey:
    """Who may send a subscriber parameters: one start of one learner. ``learner_id`` is the id its
    ``RegisterActor`` and ``Heartbeat`` replies carry; ``secret`` (random, drawn at start) travels to
    each actor in ``RegisterActorReply.params_key``. Messages are signed under :meth:`mac_key`."""

    learner_id: str
    secret: bytes = field(repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.secret, bytes) or len(self.secret) < 16:
            raise ValueError("a stream key's secret must be at least 16 random bytes (RegisterActorReply.params_key)")

    @classmethod
    def fresh(cls) -> StreamKey:
        """A new learner id and secret (each learner start)."""
        return cls(uuid.uuid4().hex, secrets.token_bytes(STREAM_SECRET_BYTES))

    def mac_key(self, token: bytes | None) -> bytes:
        """HMAC-SHA256(secret, label + learner_id), then, with a token, HMAC-SHA256(token, that): the
        learner's id is bound to the key, and with a token forging needs the token as well."""
        learner_id = self.learner_id.encode()
        key = hmac.new(self.secret, _STREAM_LABEL + len(learner_id).to_bytes(8, "little") + learner_id, hashlib.sha256)
        return key.digest() if token is None else hmac.new(token, key.digest(), hashlib.sha256).digest()


__all__ = ["STREAM_SECRET_BYTES", "StreamKey"]

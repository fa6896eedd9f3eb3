from protos import replay_pb2 as _replay_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RegisterActorRequest(_message.Message):
    __slots__ = ("name", "preferred_index")
    NAME_FIELD_NUMBER: _ClassVar[int]
    PREFERRED_INDEX_FIELD_NUMBER: _ClassVar[int]
    name: str
    preferred_index: int
    def __init__(self, name: _Optional[str] = ..., preferred_index: _Optional[int] = ...) -> None: ...

class RegisterActorReply(_message.Message):
    __slots__ = ("actor_id", "index", "learner_id", "params_port", "lease_s", "params_key", "live_actors")
    ACTOR_ID_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    PARAMS_PORT_FIELD_NUMBER: _ClassVar[int]
    LEASE_S_FIELD_NUMBER: _ClassVar[int]
    PARAMS_KEY_FIELD_NUMBER: _ClassVar[int]
    LIVE_ACTORS_FIELD_NUMBER: _ClassVar[int]
    actor_id: str
    index: int
    learner_id: str
    params_port: int
    lease_s: float
    params_key: bytes
    live_actors: int
    def __init__(self, actor_id: _Optional[str] = ..., index: _Optional[int] = ..., learner_id: _Optional[str] = ..., params_port: _Optional[int] = ..., lease_s: _Optional[float] = ..., params_key: _Optional[bytes] = ..., live_actors: _Optional[int] = ...) -> None: ...

class HeartbeatRequest(_message.Message):
    __slots__ = ("actor_id", "env_steps", "leaving")
    ACTOR_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    LEAVING_FIELD_NUMBER: _ClassVar[int]
    actor_id: str
    env_steps: int
    leaving: bool
    def __init__(self, actor_id: _Optional[str] = ..., env_steps: _Optional[int] = ..., leaving: _Optional[bool] = ...) -> None: ...

class HeartbeatReply(_message.Message):
    __slots__ = ("learner_id", "params_version", "run_done", "live_actors", "updates")
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    PARAMS_VERSION_FIELD_NUMBER: _ClassVar[int]
    RUN_DONE_FIELD_NUMBER: _ClassVar[int]
    LIVE_ACTORS_FIELD_NUMBER: _ClassVar[int]
    UPDATES_FIELD_NUMBER: _ClassVar[int]
    learner_id: str
    params_version: int
    run_done: bool
    live_actors: int
    updates: int
    def __init__(self, learner_id: _Optional[str] = ..., params_version: _Optional[int] = ..., run_done: _Optional[bool] = ..., live_actors: _Optional[int] = ..., updates: _Optional[int] = ...) -> None: ...

class GetParamsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GetParamsReply(_message.Message):
    __slots__ = ("version", "frames")
    VERSION_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    version: int
    frames: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, version: _Optional[int] = ..., frames: _Optional[_Iterable[bytes]] = ...) -> None: ...

class GetWeightsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GetActionRequest(_message.Message):
    __slots__ = ("obs", "prev_actions", "rnn_state", "noise", "deterministic")
    OBS_FIELD_NUMBER: _ClassVar[int]
    PREV_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    RNN_STATE_FIELD_NUMBER: _ClassVar[int]
    NOISE_FIELD_NUMBER: _ClassVar[int]
    DETERMINISTIC_FIELD_NUMBER: _ClassVar[int]
    obs: _containers.RepeatedCompositeFieldContainer[_replay_pb2.Tensor]
    prev_actions: _replay_pb2.Tensor
    rnn_state: _replay_pb2.Tensor
    noise: float
    deterministic: bool
    def __init__(self, obs: _Optional[_Iterable[_Union[_replay_pb2.Tensor, _Mapping]]] = ..., prev_actions: _Optional[_Union[_replay_pb2.Tensor, _Mapping]] = ..., rnn_state: _Optional[_Union[_replay_pb2.Tensor, _Mapping]] = ..., noise: _Optional[float] = ..., deterministic: _Optional[bool] = ...) -> None: ...

class GetActionReply(_message.Message):
    __slots__ = ("actions", "behaviour_logp", "rnn_state", "params_version")
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    BEHAVIOUR_LOGP_FIELD_NUMBER: _ClassVar[int]
    RNN_STATE_FIELD_NUMBER: _ClassVar[int]
    PARAMS_VERSION_FIELD_NUMBER: _ClassVar[int]
    actions: _replay_pb2.Tensor
    behaviour_logp: _replay_pb2.Tensor
    rnn_state: _replay_pb2.Tensor
    params_version: int
    def __init__(self, actions: _Optional[_Union[_replay_pb2.Tensor, _Mapping]] = ..., behaviour_logp: _Optional[_Union[_replay_pb2.Tensor, _Mapping]] = ..., rnn_state: _Optional[_Union[_replay_pb2.Tensor, _Mapping]] = ..., params_version: _Optional[int] = ...) -> None: ...

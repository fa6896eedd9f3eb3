from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Instruction(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CONTINUE: _ClassVar[Instruction]
    LOAD_WEIGHTS: _ClassVar[Instruction]
    RETIRE: _ClassVar[Instruction]

class Role(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ROLE_UNSPECIFIED: _ClassVar[Role]
    ACTOR: _ClassVar[Role]
    REPLAY: _ClassVar[Role]
CONTINUE: Instruction
LOAD_WEIGHTS: Instruction
RETIRE: Instruction
ROLE_UNSPECIFIED: Role
ACTOR: Role
REPLAY: Role

class RegisterLearnerRequest(_message.Message):
    __slots__ = ("name", "host", "learner_port", "params_port", "replay_address", "previous_id")
    NAME_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    LEARNER_PORT_FIELD_NUMBER: _ClassVar[int]
    PARAMS_PORT_FIELD_NUMBER: _ClassVar[int]
    REPLAY_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    PREVIOUS_ID_FIELD_NUMBER: _ClassVar[int]
    name: str
    host: str
    learner_port: int
    params_port: int
    replay_address: str
    previous_id: int
    def __init__(self, name: _Optional[str] = ..., host: _Optional[str] = ..., learner_port: _Optional[int] = ..., params_port: _Optional[int] = ..., replay_address: _Optional[str] = ..., previous_id: _Optional[int] = ...) -> None: ...

class RegisterLearnerReply(_message.Message):
    __slots__ = ("learner_id", "experiment", "config_yaml", "params_json", "lease_s", "replay_address", "rounds")
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    EXPERIMENT_FIELD_NUMBER: _ClassVar[int]
    CONFIG_YAML_FIELD_NUMBER: _ClassVar[int]
    PARAMS_JSON_FIELD_NUMBER: _ClassVar[int]
    LEASE_S_FIELD_NUMBER: _ClassVar[int]
    REPLAY_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    ROUNDS_FIELD_NUMBER: _ClassVar[int]
    learner_id: int
    experiment: str
    config_yaml: str
    params_json: str
    lease_s: float
    replay_address: str
    rounds: int
    def __init__(self, learner_id: _Optional[int] = ..., experiment: _Optional[str] = ..., config_yaml: _Optional[str] = ..., params_json: _Optional[str] = ..., lease_s: _Optional[float] = ..., replay_address: _Optional[str] = ..., rounds: _Optional[int] = ...) -> None: ...

class LearnerHeartbeatRequest(_message.Message):
    __slots__ = ("learner_id", "env_steps", "loaded_round")
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    LOADED_ROUND_FIELD_NUMBER: _ClassVar[int]
    learner_id: int
    env_steps: int
    loaded_round: int
    def __init__(self, learner_id: _Optional[int] = ..., env_steps: _Optional[int] = ..., loaded_round: _Optional[int] = ...) -> None: ...

class LearnerHeartbeatReply(_message.Message):
    __slots__ = ("instruction", "sample_round", "replay_address", "lease_s", "rounds")
    INSTRUCTION_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_ROUND_FIELD_NUMBER: _ClassVar[int]
    REPLAY_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    LEASE_S_FIELD_NUMBER: _ClassVar[int]
    ROUNDS_FIELD_NUMBER: _ClassVar[int]
    instruction: Instruction
    sample_round: int
    replay_address: str
    lease_s: float
    rounds: int
    def __init__(self, instruction: _Optional[_Union[Instruction, str]] = ..., sample_round: _Optional[int] = ..., replay_address: _Optional[str] = ..., lease_s: _Optional[float] = ..., rounds: _Optional[int] = ...) -> None: ...

class PostRewardRequest(_message.Message):
    __slots__ = ("learner_id", "mean_return", "env_steps", "weights_round")
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    MEAN_RETURN_FIELD_NUMBER: _ClassVar[int]
    ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_ROUND_FIELD_NUMBER: _ClassVar[int]
    learner_id: int
    mean_return: float
    env_steps: int
    weights_round: int
    def __init__(self, learner_id: _Optional[int] = ..., mean_return: _Optional[float] = ..., env_steps: _Optional[int] = ..., weights_round: _Optional[int] = ...) -> None: ...

class PostRewardReply(_message.Message):
    __slots__ = ("accepted",)
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    accepted: bool
    def __init__(self, accepted: _Optional[bool] = ...) -> None: ...

class GetSampleRequest(_message.Message):
    __slots__ = ("learner_id",)
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    learner_id: int
    def __init__(self, learner_id: _Optional[int] = ...) -> None: ...

class GetSampleReply(_message.Message):
    __slots__ = ("round", "frames")
    ROUND_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    round: int
    frames: _containers.RepeatedScalarFieldContainer[bytes]
    def __init__(self, round: _Optional[int] = ..., frames: _Optional[_Iterable[bytes]] = ...) -> None: ...

class AssignRequest(_message.Message):
    __slots__ = ("role", "name", "address", "previous_assignment_id")
    ROLE_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    PREVIOUS_ASSIGNMENT_ID_FIELD_NUMBER: _ClassVar[int]
    role: Role
    name: str
    address: str
    previous_assignment_id: str
    def __init__(self, role: _Optional[_Union[Role, str]] = ..., name: _Optional[str] = ..., address: _Optional[str] = ..., previous_assignment_id: _Optional[str] = ...) -> None: ...

class Assignment(_message.Message):
    __slots__ = ("assignment_id", "role", "learner_id", "learner_host", "learner_port", "params_port", "replay_address", "config_yaml", "experiment", "lease_s", "learner_live")
    ASSIGNMENT_ID_FIELD_NUMBER: _ClassVar[int]
    ROLE_FIELD_NUMBER: _ClassVar[int]
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    LEARNER_HOST_FIELD_NUMBER: _ClassVar[int]
    LEARNER_PORT_FIELD_NUMBER: _ClassVar[int]
    PARAMS_PORT_FIELD_NUMBER: _ClassVar[int]
    REPLAY_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    CONFIG_YAML_FIELD_NUMBER: _ClassVar[int]
    EXPERIMENT_FIELD_NUMBER: _ClassVar[int]
    LEASE_S_FIELD_NUMBER: _ClassVar[int]
    LEARNER_LIVE_FIELD_NUMBER: _ClassVar[int]
    assignment_id: str
    role: Role
    learner_id: int
    learner_host: str
    learner_port: int
    params_port: int
    replay_address: str
    config_yaml: str
    experiment: str
    lease_s: float
    learner_live: bool
    def __init__(self, assignment_id: _Optional[str] = ..., role: _Optional[_Union[Role, str]] = ..., learner_id: _Optional[int] = ..., learner_host: _Optional[str] = ..., learner_port: _Optional[int] = ..., params_port: _Optional[int] = ..., replay_address: _Optional[str] = ..., config_yaml: _Optional[str] = ..., experiment: _Optional[str] = ..., lease_s: _Optional[float] = ..., learner_live: _Optional[bool] = ...) -> None: ...

class AssignmentHeartbeatRequest(_message.Message):
    __slots__ = ("assignment_id",)
    ASSIGNMENT_ID_FIELD_NUMBER: _ClassVar[int]
    assignment_id: str
    def __init__(self, assignment_id: _Optional[str] = ...) -> None: ...

class EvolverInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class LearnerInfo(_message.Message):
    __slots__ = ("learner_id", "name", "host", "learner_port", "params_port", "replay_address", "mean_return", "returns", "rounds", "times_elite", "retired", "live", "params_json", "actors", "env_steps", "pending_round")
    LEARNER_ID_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    LEARNER_PORT_FIELD_NUMBER: _ClassVar[int]
    PARAMS_PORT_FIELD_NUMBER: _ClassVar[int]
    REPLAY_ADDRESS_FIELD_NUMBER: _ClassVar[int]
    MEAN_RETURN_FIELD_NUMBER: _ClassVar[int]
    RETURNS_FIELD_NUMBER: _ClassVar[int]
    ROUNDS_FIELD_NUMBER: _ClassVar[int]
    TIMES_ELITE_FIELD_NUMBER: _ClassVar[int]
    RETIRED_FIELD_NUMBER: _ClassVar[int]
    LIVE_FIELD_NUMBER: _ClassVar[int]
    PARAMS_JSON_FIELD_NUMBER: _ClassVar[int]
    ACTORS_FIELD_NUMBER: _ClassVar[int]
    ENV_STEPS_FIELD_NUMBER: _ClassVar[int]
    PENDING_ROUND_FIELD_NUMBER: _ClassVar[int]
    learner_id: int
    name: str
    host: str
    learner_port: int
    params_port: int
    replay_address: str
    mean_return: float
    returns: int
    rounds: int
    times_elite: int
    retired: bool
    live: bool
    params_json: str
    actors: int
    env_steps: int
    pending_round: int
    def __init__(self, learner_id: _Optional[int] = ..., name: _Optional[str] = ..., host: _Optional[str] = ..., learner_port: _Optional[int] = ..., params_port: _Optional[int] = ..., replay_address: _Optional[str] = ..., mean_return: _Optional[float] = ..., returns: _Optional[int] = ..., rounds: _Optional[int] = ..., times_elite: _Optional[int] = ..., retired: _Optional[bool] = ..., live: _Optional[bool] = ..., params_json: _Optional[str] = ..., actors: _Optional[int] = ..., env_steps: _Optional[int] = ..., pending_round: _Optional[int] = ...) -> None: ...

class EvolverInfoReply(_message.Message):
    __slots__ = ("experiment", "rounds", "last_elites", "learners", "assignments")
    EXPERIMENT_FIELD_NUMBER: _ClassVar[int]
    ROUNDS_FIELD_NUMBER: _ClassVar[int]
    LAST_ELITES_FIELD_NUMBER: _ClassVar[int]
    LEARNERS_FIELD_NUMBER: _ClassVar[int]
    ASSIGNMENTS_FIELD_NUMBER: _ClassVar[int]
    experiment: str
    rounds: int
    last_elites: _containers.RepeatedScalarFieldContainer[int]
    learners: _containers.RepeatedCompositeFieldContainer[LearnerInfo]
    assignments: _containers.RepeatedCompositeFieldContainer[Assignment]
    def __init__(self, experiment: _Optional[str] = ..., rounds: _Optional[int] = ..., last_elites: _Optional[_Iterable[int]] = ..., learners: _Optional[_Iterable[_Union[LearnerInfo, _Mapping]]] = ..., assignments: _Optional[_Iterable[_Union[Assignment, _Mapping]]] = ...) -> None: ...

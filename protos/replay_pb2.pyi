from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Tensor(_message.Message):
    __slots__ = ("dtype", "shape", "data")
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    def __init__(self, dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ...) -> None: ...

class Chunk(_message.Message):
    __slots__ = ("obs", "actions", "prev_actions", "rewards", "terminated", "truncated", "behaviour_logp", "rnn_state", "priorities")
    OBS_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    PREV_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    REWARDS_FIELD_NUMBER: _ClassVar[int]
    TERMINATED_FIELD_NUMBER: _ClassVar[int]
    TRUNCATED_FIELD_NUMBER: _ClassVar[int]
    BEHAVIOUR_LOGP_FIELD_NUMBER: _ClassVar[int]
    RNN_STATE_FIELD_NUMBER: _ClassVar[int]
    PRIORITIES_FIELD_NUMBER: _ClassVar[int]
    obs: _containers.RepeatedCompositeFieldContainer[Tensor]
    actions: Tensor
    prev_actions: Tensor
    rewards: Tensor
    terminated: Tensor
    truncated: Tensor
    behaviour_logp: Tensor
    rnn_state: Tensor
    priorities: Tensor
    def __init__(self, obs: _Optional[_Iterable[_Union[Tensor, _Mapping]]] = ..., actions: _Optional[_Union[Tensor, _Mapping]] = ..., prev_actions: _Optional[_Union[Tensor, _Mapping]] = ..., rewards: _Optional[_Union[Tensor, _Mapping]] = ..., terminated: _Optional[_Union[Tensor, _Mapping]] = ..., truncated: _Optional[_Union[Tensor, _Mapping]] = ..., behaviour_logp: _Optional[_Union[Tensor, _Mapping]] = ..., rnn_state: _Optional[_Union[Tensor, _Mapping]] = ..., priorities: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class InsertRequest(_message.Message):
    __slots__ = ("chunks", "timeout_s", "producer", "sequence", "acked_below", "producer_stopping")
    CHUNKS_FIELD_NUMBER: _ClassVar[int]
    TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    PRODUCER_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    ACKED_BELOW_FIELD_NUMBER: _ClassVar[int]
    PRODUCER_STOPPING_FIELD_NUMBER: _ClassVar[int]
    chunks: _containers.RepeatedCompositeFieldContainer[Chunk]
    timeout_s: float
    producer: int
    sequence: _containers.RepeatedScalarFieldContainer[int]
    acked_below: int
    producer_stopping: bool
    def __init__(self, chunks: _Optional[_Iterable[_Union[Chunk, _Mapping]]] = ..., timeout_s: _Optional[float] = ..., producer: _Optional[int] = ..., sequence: _Optional[_Iterable[int]] = ..., acked_below: _Optional[int] = ..., producer_stopping: _Optional[bool] = ...) -> None: ...

class InsertReply(_message.Message):
    __slots__ = ("keys", "duplicate", "inserted_steps", "served_s")
    KEYS_FIELD_NUMBER: _ClassVar[int]
    DUPLICATE_FIELD_NUMBER: _ClassVar[int]
    INSERTED_STEPS_FIELD_NUMBER: _ClassVar[int]
    SERVED_S_FIELD_NUMBER: _ClassVar[int]
    keys: _containers.RepeatedCompositeFieldContainer[Tensor]
    duplicate: _containers.RepeatedScalarFieldContainer[bool]
    inserted_steps: int
    served_s: float
    def __init__(self, keys: _Optional[_Iterable[_Union[Tensor, _Mapping]]] = ..., duplicate: _Optional[_Iterable[bool]] = ..., inserted_steps: _Optional[int] = ..., served_s: _Optional[float] = ...) -> None: ...

class SampleRequest(_message.Message):
    __slots__ = ("batch_size", "timeout_s", "batches", "shared_name", "shared_size", "shared_seq")
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    TIMEOUT_S_FIELD_NUMBER: _ClassVar[int]
    BATCHES_FIELD_NUMBER: _ClassVar[int]
    SHARED_NAME_FIELD_NUMBER: _ClassVar[int]
    SHARED_SIZE_FIELD_NUMBER: _ClassVar[int]
    SHARED_SEQ_FIELD_NUMBER: _ClassVar[int]
    batch_size: int
    timeout_s: float
    batches: int
    shared_name: str
    shared_size: int
    shared_seq: int
    def __init__(self, batch_size: _Optional[int] = ..., timeout_s: _Optional[float] = ..., batches: _Optional[int] = ..., shared_name: _Optional[str] = ..., shared_size: _Optional[int] = ..., shared_seq: _Optional[int] = ...) -> None: ...

class SampleReply(_message.Message):
    __slots__ = ("batch_size", "window", "table_size", "data", "shared_bytes")
    BATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    WINDOW_FIELD_NUMBER: _ClassVar[int]
    TABLE_SIZE_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    SHARED_BYTES_FIELD_NUMBER: _ClassVar[int]
    batch_size: int
    window: int
    table_size: _containers.RepeatedScalarFieldContainer[int]
    data: bytes
    shared_bytes: int
    def __init__(self, batch_size: _Optional[int] = ..., window: _Optional[int] = ..., table_size: _Optional[_Iterable[int]] = ..., data: _Optional[bytes] = ..., shared_bytes: _Optional[int] = ...) -> None: ...

class WindowsRequest(_message.Message):
    __slots__ = ("from_key", "max_windows")
    FROM_KEY_FIELD_NUMBER: _ClassVar[int]
    MAX_WINDOWS_FIELD_NUMBER: _ClassVar[int]
    from_key: int
    max_windows: int
    def __init__(self, from_key: _Optional[int] = ..., max_windows: _Optional[int] = ...) -> None: ...

class UpdatePrioritiesRequest(_message.Message):
    __slots__ = ("keys", "priorities")
    KEYS_FIELD_NUMBER: _ClassVar[int]
    PRIORITIES_FIELD_NUMBER: _ClassVar[int]
    keys: Tensor
    priorities: Tensor
    def __init__(self, keys: _Optional[_Union[Tensor, _Mapping]] = ..., priorities: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class UpdatePrioritiesReply(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class UpdateRnnStatesRequest(_message.Message):
    __slots__ = ("keys", "states")
    KEYS_FIELD_NUMBER: _ClassVar[int]
    STATES_FIELD_NUMBER: _ClassVar[int]
    keys: Tensor
    states: Tensor
    def __init__(self, keys: _Optional[_Union[Tensor, _Mapping]] = ..., states: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class UpdateRnnStatesReply(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class InfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class NormalizerStats(_message.Message):
    __slots__ = ("count", "mean", "var")
    COUNT_FIELD_NUMBER: _ClassVar[int]
    MEAN_FIELD_NUMBER: _ClassVar[int]
    VAR_FIELD_NUMBER: _ClassVar[int]
    count: int
    mean: Tensor
    var: Tensor
    def __init__(self, count: _Optional[int] = ..., mean: _Optional[_Union[Tensor, _Mapping]] = ..., var: _Optional[_Union[Tensor, _Mapping]] = ...) -> None: ...

class InfoReply(_message.Message):
    __slots__ = ("counters", "values", "normalizer")
    class CountersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    class ValuesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    class NormalizerEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: NormalizerStats
        def __init__(self, key: _Optional[str] = ..., value: _Optional[_Union[NormalizerStats, _Mapping]] = ...) -> None: ...
    COUNTERS_FIELD_NUMBER: _ClassVar[int]
    VALUES_FIELD_NUMBER: _ClassVar[int]
    NORMALIZER_FIELD_NUMBER: _ClassVar[int]
    counters: _containers.ScalarMap[str, int]
    values: _containers.ScalarMap[str, float]
    normalizer: _containers.MessageMap[str, NormalizerStats]
    def __init__(self, counters: _Optional[_Mapping[str, int]] = ..., values: _Optional[_Mapping[str, float]] = ..., normalizer: _Optional[_Mapping[str, NormalizerStats]] = ...) -> None: ...

class SaveRequest(_message.Message):
    __slots__ = ("path",)
    PATH_FIELD_NUMBER: _ClassVar[int]
    path: str
    def __init__(self, path: _Optional[str] = ...) -> None: ...

class SaveReply(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class LoadRequest(_message.Message):
    __slots__ = ("path",)
    PATH_FIELD_NUMBER: _ClassVar[int]
    path: str
    def __init__(self, path: _Optional[str] = ...) -> None: ...

class LoadReply(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

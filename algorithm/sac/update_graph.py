"""Recording the forward and backward pass of :meth:`algorithm.sac.learner.SAC.update` once as a CUDA graph and
replaying it for every batch (``sac_config.cuda_graph``).

On a GPU an update of MuJoCo-sized networks is bound by launching its ~230 kernels one by one from Python,
not by the GPU: on an H100 one HalfCheetah update (256x256, batch 256) took 12.6 ms of wall time of which
the GPU was busy 0.58 ms (BENCHMARKS.md section 12). A CUDA graph records those launches once and replays
them as one. What stays outside the graph, run eagerly as without it: moving the batch into the graph's
input buffers, the noise draws (the same generator stream as without the graph), the non-finite check's
one host sync, the optimizer steps and the target update. So an update computes the same with and without
the graph (tests/algorithm/sac/test_update_graph.py compares the weights after many updates); on an H200 it
made 5.9x the updates per second with bit-identical weights (bench/results/gpu/README.md).

Recording follows PyTorch's recipe for capturing a whole training step (the CUDA semantics notes, "CUDA
Graphs"): a few warm-up passes on a side stream first, gradients set to None before recording so that the
backward pass allocates them in the graph's memory pool (each replay overwrites them there), and autocast
without its cast cache. Passes whose shapes depend on the data (V-trace's and normalized RND's boolean-mask
indexing) cannot be recorded as they are written; prediction models (a second autograd pass) and recurrent
windows were not tried on a GPU. Those configs run eagerly (:func:`why_not_graphed`); a recording that
fails anyway is logged and the update runs eagerly after :data:`MAX_FAILED_RECORDINGS` tries.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from algorithm.config.schema import SacConfig

log = logging.getLogger("asac.update_graph")

WARMUP_PASSES = 2  # PyTorch's recipe warms up before capture (lazy cuBLAS/autograd setup happens off the record)
MAX_FAILED_RECORDINGS = 3

Inputs = Sequence["np.ndarray | Tensor | None"]


class Recorder(Protocol):
    """Records a pass once and replays it. :class:`CudaGraphRecorder` on a GPU; the tests' stand-in
    replays by running the pass again, to check the buffers' plumbing where there is no GPU."""

    def record(self, run: Callable[[], Any]) -> Any:
        """Record ``run``; returns what it returned, whose tensors each :meth:`replay` rewrites."""
        ...

    def replay(self) -> None: ...


class CudaGraphRecorder:
    """A ``torch.cuda.CUDAGraph`` of the pass, warmed up on a side stream first."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self._graph: torch.cuda.CUDAGraph | None = None

    def record(self, run: Callable[[], Any]) -> Any:
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            for _ in range(WARMUP_PASSES):
                run()
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        # thread_local: other threads of a learner role (weights publishing, scoring) may use the GPU
        # meanwhile; only this thread's calls must be capturable.
        with torch.cuda.graph(graph, capture_error_mode="thread_local"):
            out = run()
        self._graph = graph
        return out

    def replay(self) -> None:
        assert self._graph is not None, "replay() before record()"
        self._graph.replay()


def why_not_graphed(
    sac: SacConfig, device: torch.device, compiled: bool, has_rnn: bool, has_prediction: bool
) -> str | None:
    """None when updates on ``device`` are recorded as a CUDA graph, else why not (logged once on a GPU)."""
    if device.type != "cuda":
        return "not a CUDA device"
    reasons = [
        (not sac.cuda_graph, "sac_config.cuda_graph is false"),
        (compiled, "sac_config.compile is on (torch.compile records its own graphs)"),
        (has_rnn, "use_rnn: recurrent windows are not recorded"),
        (sac.train_every_step, "train_every_step is not recorded"),
        (sac.update_order == "critic_first", "update_order critic_first: the policy's pass follows the critic's step"),
        (sac.use_n_step_is, "use_n_step_is: V-trace's metrics index by a data-dependent mask"),
        (has_prediction, "prediction models take a second autograd pass"),
        (sac.use_rnd and sac.rnd_normalize, "rnd_normalize: the novelty mean indexes by a data-dependent mask"),
    ]
    return next((why for hit, why in reasons if hit), None)


def graph_for(sac: SacConfig, device: torch.device, compiled: bool, has_rnn: bool, has_prediction: bool,
              params: Sequence[Tensor]) -> UpdateGraph | None:  # fmt: skip
    """The :class:`UpdateGraph` of a SAC on ``device`` training ``params``, or None (on a GPU, logged why)."""
    why = why_not_graphed(sac, device, compiled, has_rnn, has_prediction)
    if why is None:
        return UpdateGraph(lambda: CudaGraphRecorder(device), params)
    if device.type == "cuda":
        log.info("updates run without a CUDA graph: %s", why)
    return None


class UpdateGraph:
    """The recorded pass and its fixed input buffers: :meth:`run` copies each batch into the buffers,
    replays, and points every parameter's ``.grad`` at the gradients the replay wrote."""

    def __init__(self, recorder_factory: Callable[[], Recorder], params: Sequence[Tensor]) -> None:
        self._new_recorder = recorder_factory
        self._params = list(params)
        self._recorder: Recorder | None = None
        self._inputs: list[Tensor | None] = []
        self._signature: tuple[Any, ...] | None = None
        self._out: Any = None
        self._grads: list[tuple[Tensor, Tensor]] = []
        self.recordings = 0
        self.failed = 0

    @property
    def usable(self) -> bool:
        return self.failed < MAX_FAILED_RECORDINGS

    def run(
        self,
        step: Callable[[list[Tensor | None]], Any],
        inputs: Inputs,
        device: torch.device,
        keep: Sequence[torch.nn.Module],
    ) -> Any | None:
        """``step(buffers)`` replayed on ``inputs``; None when recording it failed (run it eagerly then).
        ``keep``: modules whose buffers the warm-up passes must leave as they were."""
        signature = tuple(_signature(x) for x in inputs)
        if signature != self._signature and not self._record(step, inputs, signature, device, keep):
            return None
        for buffer, x in zip(self._inputs, inputs, strict=True):
            if buffer is not None and x is not None:  # the signature matched: both or neither
                buffer.copy_(torch.from_numpy(x) if isinstance(x, np.ndarray) else x, non_blocking=True)
        assert self._recorder is not None
        self._recorder.replay()
        for p, g in self._grads:  # an optimizer's zero_grad(set_to_none) may have let go of them
            p.grad = g
        return self._out

    def _record(self, step: Callable[[list[Tensor | None]], Any], inputs: Inputs, signature: tuple[Any, ...],
                device: torch.device, keep: Sequence[torch.nn.Module]) -> bool:  # fmt: skip
        self._signature, self._out, self._grads = None, None, []
        buffers = [None if x is None else _to_device(x, device).clone() for x in inputs]
        kept = [b.detach().clone() for m in keep for b in m.buffers()]
        recorder = self._new_recorder()

        def run() -> tuple[Any, list[Tensor | None]]:
            out = step(buffers)
            return out, [p.grad for p in self._params]

        try:
            out, grads = recorder.record(run)
        except Exception as error:  # noqa: BLE001 - any failure to record means: run eagerly
            self.failed += 1
            later = "trying again at the next update" if self.usable else "updates run without it from now on"
            log.warning("could not record the update as a CUDA graph (%s: %s); %s", type(error).__name__,
                        str(error)[:300], later)  # fmt: skip
            return False
        finally:
            with torch.no_grad():
                for b, saved in zip((b for m in keep for b in m.buffers()), kept, strict=True):
                    b.copy_(saved)
        self._recorder, self._inputs, self._signature, self._out = recorder, buffers, signature, out
        self._grads = [(p, g) for p, g in zip(self._params, grads, strict=True) if g is not None]
        self.recordings += 1
        if self.recordings == 1:
            log.info("updates replay a CUDA graph of their forward and backward pass (sac_config.cuda_graph)")
        return True


def _to_device(x: np.ndarray | Tensor, device: torch.device) -> Tensor:
    return (torch.from_numpy(x) if isinstance(x, np.ndarray) else x).to(device, non_blocking=True)


def _signature(x: np.ndarray | Tensor | None) -> tuple[Any, ...] | None:
    return None if x is None else (tuple(x.shape), str(x.dtype))

"""The typed config schema: one pydantic model per section, one documented field per key.

Section and key names follow the original Advanced-Soft-Actor-Critic so its users feel at home; new
sections (``nn_config``, ``actor_config``, ``eval_config``) hold keys for parts it did not have.
Every model forbids unknown keys; :mod:`algorithm.config.load` layers YAML files onto these models and
turns validation errors into messages that name the key and the file.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from algorithm.config.random_params import parse_random_params

# The largest extra exploration noise (a std added before the tanh) acting accepts (algorithm/sac/policy.py,
# the learner's GetAction, main_ds.py --noise). Far past it tanh saturates every action anyway; near
# 1e37 the float32 std overflows and log-probs become NaN.
MAX_EXPLORATION_NOISE = 1e6


class Section(BaseModel):
    """Base for every section: unknown keys are errors, assignments are validated, and no number may
    be NaN or infinite (``.inf`` passed ``learning_rate > 0``; a NaN ``init_log_alpha`` trained NaNs)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, strict=False, allow_inf_nan=False)


class BaseConfig(Section):
    env_type: Literal["GYM"] = Field("GYM", description="Environment family; Unity is out of scope.")
    scene: str = Field("scene", description="Readable task name shown in TensorBoard.")
    build_path: str = Field("Pendulum-v1", description="Gymnasium id, e.g. 'HalfCheetah-v5'.")
    env_kwargs: dict[str, Any] = Field(default_factory=dict, description="Extra kwargs for gymnasium.make.")
    name: str = Field("{time}", description="Run name; '{time}' becomes the start time.")
    nn: str = Field("nn", description="Model file in the task folder (nn.py) when it exists.")
    n_agents: int = Field(1, ge=1, description="Parallel envs stepped by the actor.")
    max_iter: int = Field(-1, ge=-1, description="Stop after this many iterations (episodes of env 0); -1 off.")
    max_step: int = Field(-1, ge=-1, description="Stop after this many env steps over all envs; -1 off.")
    max_step_each_iter: int = Field(-1, ge=-1, description="Time limit per episode in steps; -1 = env's own.")
    reset_on_iteration: bool = Field(
        False,
        description="When env 0's episode ends, cut (truncate) and reset every other env too, so all envs start the "
        "next iteration together. Off (default): each env runs its own episodes, as gymnasium's vector envs do. On, "
        "an early-terminating task's data skews toward episode starts (the other envs rarely reach later states).",
    )
    torch_threads: int = Field(0, ge=0, description="torch.set_num_threads; 0 leaves torch's default.")
    evolver_enabled: bool = Field(False, description="Run an evolver: a population of learners improved by CEM.")
    evolver_cem_length: int = Field(
        50, ge=1, description="A CEM round runs when every learner has posted this many evaluation returns."
    )
    evolver_cem_best: float = Field(
        0.3, gt=0.0, le=1.0, description="Elite fraction of the population (at least one learner)."
    )
    evolver_cem_min_length: int = Field(
        2, ge=1, description="Returns each learner needs before a time-triggered round (evolver_cem_time)."
    )
    evolver_cem_time: float = Field(
        3.0, gt=0, description="Minutes after the last round when a round runs with evolver_cem_min_length returns."
    )
    evolver_remove_worst: int = Field(
        4, ge=-1, description="Retire a learner after this many CEM rounds without ever being elite; -1 = off."
    )
    evolver_cem_std_max: float = Field(
        0.1,
        gt=0.0,
        description="Cap on the per-weight std of the Gaussian fitted to the elites' weights, so a CEM round "
        "never scatters weights wider than this (a new key, not in the original system).",
    )
    max_actors_each_learner: int = Field(10, ge=1, description="Distributed actors one learner accepts.")

    @model_validator(mode="after")
    def _check_evolver(self) -> BaseConfig:
        if self.evolver_cem_min_length > self.evolver_cem_length:
            raise ValueError("evolver_cem_min_length must be <= evolver_cem_length")
        if self.evolver_remove_worst == 0:
            raise ValueError("evolver_remove_worst must be -1 (off) or >= 1")
        return self


class ReplayConfig(Section):
    batch_size: int = Field(256, ge=1)
    capacity: int = Field(524288, ge=2, description="Rows stored (steps plus one bootstrap row per chunk).")
    alpha: float = Field(0.9, ge=0.0, le=1.0, description="Priority exponent; 0 = uniform replay.")
    beta: float = Field(0.4, ge=0.0, le=1.0, description="Initial importance-sampling exponent.")
    beta_increment_per_sampling: float = Field(0.001, ge=0.0, description="Added to beta per update, up to 1.")
    td_error_min: float = Field(0.01, gt=0.0, description="Floor of |TD| before ** alpha.")
    td_error_max: float = Field(1.0, gt=0.0, description="Ceiling of |TD| before ** alpha.")
    samples_per_insert: float | None = Field(
        None,
        gt=0.0,
        description="Sampled windows per inserted step (samples_per_insert / batch_size updates per env step); "
        "null = batch_size, one update per env step.",
    )
    samples_per_insert_tolerance: float = Field(
        0.0, ge=0.0, description="How many windows the learner may run ahead/behind before blocking (distributed)."
    )
    min_size_to_sample: int = Field(1000, ge=1, description="Steps stored before the first update.")
    save_replay: bool = Field(False, description="Save replay contents with checkpoints and restore them.")
    save_replay_on_stop: bool = Field(
        True,
        description="Save replay contents when a run is interrupted (Ctrl-C, SIGTERM), so that the same command "
        "resumes with the data it had; the periodic checkpoints save it only with save_replay.",
    )
    save_replay_per_minute: float | None = Field(
        None,
        gt=0,
        description="Replay role with save_replay: snapshot the table every N minutes (and at shutdown); "
        "null = sac.save_model_per_minute. What a crash loses is what came in since the last snapshot.",
    )
    max_producers: int = Field(
        1024,
        ge=1,
        description="Producers (actor processes; a restarted actor is a new one) whose chunk ids the replay keeps "
        "so that a re-sent chunk is stored at most once (algorithm/replay/dedup.py). An actor that stops acknowledges "
        "everything and gives its place up; one that is killed keeps it for the life of the replay and its "
        "snapshots; a new producer past the bound "
        "is refused (its inserts fail with RESOURCE_EXHAUSTED) rather than another producer's ids forgotten.",
    )

    @model_validator(mode="after")
    def _check_td_range(self) -> ReplayConfig:
        if self.td_error_min > self.td_error_max:
            raise ValueError("td_error_min must be <= td_error_max")
        if self.min_size_to_sample > self.capacity - 1:  # a chunk's bootstrap row takes one row
            raise ValueError(
                f"min_size_to_sample ({self.min_size_to_sample}) must be < capacity ({self.capacity}): "
                "at most capacity - 1 steps are stored, so sampling would never start"
            )
        return self

    @property
    def updates_per_step(self) -> float:
        """Gradient updates owed per env step: the explicit update-to-data ratio."""
        return (self.samples_per_insert or self.batch_size) / self.batch_size


class SacConfig(Section):
    seed: int | None = Field(None, description="Seeds torch, numpy and every env (per env index).")
    write_summary_per_step: int = Field(1000, ge=1, description="TensorBoard write interval in updates.")
    save_model_per_step: int = Field(100000, ge=1, description="Checkpoint every N env steps.")
    save_model_per_minute: float = Field(5, gt=0, description="... or every N minutes, whichever comes first.")
    keep_checkpoints: int = Field(3, ge=1, description="How many checkpoints model/ keeps.")
    ensemble_q_num: int = Field(2, ge=1, description="Q heads in the ensemble.")
    ensemble_q_sample: int = Field(2, ge=1, description="Heads in each random subset a minimum is taken over.")
    burn_in_step: int = Field(0, ge=0, description="Steps before the trained one that warm up the recurrent state.")
    burn_in_gradient: bool = Field(
        True,
        description="Let gradients flow through the burn-in steps. Off, the recurrent cell gets one step of "
        "backpropagation through time and cannot learn what to remember (gym/pendulum_novel: -950 vs -190).",
    )
    n_step: int = Field(1, ge=1)
    train_every_step: bool = Field(
        False,
        description="Train every stored step of a sampled window as the sampled one is, each with its n-step target "
        "cut at the window's end (R2D2's way with sequences), not the sampled step alone: use_rnn with burn-in "
        "trains burn_in_step + n_step steps per window (only the n_step after the burn-in without "
        "burn_in_gradient), at about the cost of one. Priorities stay the sampled step's.",
    )
    use_rnn: bool = Field(False, description="Recurrent representation (nn_config.rnn_type, rnn_units).")
    tau: float = Field(0.005, gt=0.0, le=1.0)
    update_target_per_step: int = Field(1, ge=1)
    update_policy_variables_per_step: int = Field(
        1, ge=1, description="Actors get the learner's weights every N updates (1: always current)."
    )
    publish_budget: float = Field(
        0.02,
        ge=0.0,
        lt=1.0,
        description="Distributed learner: the most of its time publishing the acting weights may take (copying, "
        "signing, sending); after a publish that took t seconds the next waits until t / publish_budget seconds "
        "have passed (and update_policy_variables_per_step updates). 0: publish at every such update. main.py's "
        "actors act with the weights of every update_policy_variables_per_step-th update, whatever this is.",
    )
    init_log_alpha: float = -2.3
    use_auto_alpha: bool = True
    learning_rate: float = Field(3e-4, gt=0.0)
    gamma: float = Field(0.99, ge=0.0, le=1.0)
    v_lambda: float = Field(1.0, ge=0.0, le=1.0)
    v_rho: float = Field(1.0, gt=0.0)
    v_c: float = Field(1.0, gt=0.0)
    clip_epsilon: float | None = Field(
        None, gt=0.0, description="Value clipping around the target head; null = off (the original used 0.2)."
    )
    discrete_dqn_like: bool = Field(False, description="Learn the discrete part as double DQN, epsilon-greedy.")
    discrete_dqn_epsilon: float = Field(0.2, ge=0.0, le=1.0, description="Exploration rate of discrete_dqn_like.")
    discrete_target_entropy_ratio: float = Field(
        0.98, gt=0.0, le=1.0, description="Discrete target entropy per branch, as a fraction of log|A_b|."
    )
    discrete_target_entropy_start: float | None = Field(
        None,
        gt=0.0,
        le=1.0,
        description="Anneal the discrete target entropy ratio from this value down to discrete_target_entropy_ratio "
        "over discrete_target_entropy_anneal_updates updates (TES-SAC); null = constant.",
    )
    discrete_target_entropy_anneal_updates: int = Field(
        10000, ge=1, description="Updates over which the discrete target entropy moves to its final ratio."
    )
    update_order: Literal["joint", "critic_first"] = Field(
        "joint",
        description="joint: every loss from the same weights, applied together (a non-finite step is skipped "
        "whole); critic_first: the critic and temperature step first and the policy's loss is computed against "
        "the stepped critic (SB3's order; no CUDA graph).",
    )
    tanh_log_det_epsilon: float = Field(
        0.0,
        ge=0.0,
        le=0.01,
        description="The learner's losses take the policy's tanh change of variables as log(1 - tanh(u)^2 + "
        "epsilon); 0 computes it exactly. SB3 adds 1e-6, which holds the penalty on saturated actions near "
        "log(1e-6) past |u| ~ 6.5. Acting and V-trace's stored-action densities stay exact.",
    )
    discrete_entropy_penalty: float = Field(
        0.0,
        ge=0.0,
        description="Add this times (H(pi(s)) - H(mu(s)))^2 to the policy's loss, mu the policy that acted "
        "(SD-SAC's entropy penalty, Zhou et al.; they use 0.5); discrete actions only; 0 = off.",
    )
    munchausen_scale: float = Field(
        0.0,
        ge=0.0,
        lt=1.0,
        description="Munchausen RL (Vieillard et al. 2020): add this times clip(alpha_b log pi_b(a_b|s), "
        "munchausen_log_floor, 0) to every reward of the target's window, pi the current policy; an implicit "
        "KL penalty toward the previous policy that widens action gaps (they use 0.9); discrete actions "
        "only, not with use_n_step_is; 0 = off.",
    )
    munchausen_scale_start: float | None = Field(
        None,
        ge=0.0,
        lt=1.0,
        description="Move munchausen_scale's weight linearly from this value to munchausen_scale on the step "
        "size's schedule (over learning_rate_anneal_updates updates; needs learning_rate_final), constant after; "
        "null = munchausen_scale throughout.",
    )
    munchausen_log_floor: float = Field(
        -1.0,
        le=0.0,
        description="The floor of munchausen_scale's term alpha_b log pi_b(a_b|s) (theirs: -1).",
    )
    learning_rate_final: float | None = Field(
        None,
        ge=0.0,
        description="Anneal every optimizer's step size linearly from learning_rate to this value over "
        "learning_rate_anneal_updates updates, constant after; null = constant learning_rate.",
    )
    learning_rate_anneal_updates: int | None = Field(
        None,
        ge=1,
        description="Updates over which the step size moves to learning_rate_final; null = over the run: "
        "replay_config.updates_per_step x (base_config.max_step - replay_config.min_size_to_sample), filled in "
        "when the config is read (as SB3's schedules follow the run's progress).",
    )
    use_priority: bool = Field(True, description="Weight the Q loss by PER importance weights.")
    use_n_step_is: bool = Field(False, description="V-trace correction of n-step targets.")
    use_prediction: bool = Field(False, description="Transition/reward/observation models shape the representation.")
    transition_kl: float = Field(0.8, ge=0.0, description="Weight of the transition model's KL to N(0, I).")
    use_extra_data: bool = Field(True, description="The observation model also reconstructs critic_only sensors.")
    use_curiosity: bool = Field(False, description="Intrinsic reward from a forward model's error, in targets only.")
    curiosity_strength: float = Field(1.0, ge=0.0, description="Scale of the curiosity reward.")
    curiosity_inverse: bool = Field(False, description="Learn curiosity features with an inverse model (ICM).")
    use_rnd: bool = Field(False, description="Act with the most novel of rnd_n_sample policy actions (RND).")
    rnd_n_sample: int = Field(10, ge=1, description="Policy actions drawn per step to pick the most novel from.")
    rnd_strength: float = Field(
        0.0, ge=0.0, description="Scale of RND's novelty as an intrinsic reward, in targets only (0: none)."
    )
    rnd_choice_steps: int = Field(
        0,
        ge=0,
        description="Act with the most novel candidate for the first this many of the actor's env steps, with the "
        "policy's own sample after them (0: the most novel for the whole run). Actors that ask the learner for "
        "every action (actor_config.update_policy_mode: false) keep the choice.",
    )
    rnd_choice_until_return: float | None = Field(
        None,
        description="Act with the most novel candidate until an episode of the actor returns at least this (the "
        "goal found), with the policy's own sample after it (None: no such end). main.py keeps the best return "
        "across a resume; a distributed actor that restarts starts its choice again.",
    )
    rnd_normalize: bool = Field(
        False,
        description="RND's novelty reward as rnd_strength x (novelty / m - 1), m a running mean of the replayed "
        "pairs' novelty: a scale that does not fade, zero on average, pairs newer than the rest rewarded.",
    )
    action_noise_color: float = Field(
        0.0,
        ge=0.0,
        description="Exponent beta of the acting noise's power spectrum 1/f^beta along each env's steps: 0 draws it "
        "afresh every step (SAC's default), 1 is pink, 2 red (Eberhard et al. 2023). Each step's noise stays a "
        "standard normal, so actions keep the policy's distribution and behaviour log-probs stay exact.",
    )
    use_normalization: bool = False
    max_nonfinite_steps: int = Field(100, ge=1, description="Consecutive skipped (non-finite) updates before stopping.")
    compile: bool = Field(False, description="torch.compile the losses; 5-10% slower on CPU (bench/learner.py).")
    cuda_graph: bool = Field(
        True,
        description="On a CUDA device, record each update's forward and backward pass once as a CUDA graph and "
        "replay it (algorithm/sac/update_graph.py): the same result without launching ~230 kernels from Python per "
        "update. Recurrent, V-trace, prediction-model and normalized-RND configs run eagerly; no effect on the CPU.",
    )
    numpy_acting: bool = Field(
        True,
        description="Act with a NumPy copy of the policy's forward pass where it computes exactly what torch "
        "would (vector sensors, MLP tanh-Gaussian policy, CPU; algorithm/nn/numpy_acting.py): several times "
        "faster per env step for actors. false always acts with torch.",
    )
    refresh_rnn_states: bool = Field(
        False,
        description="use_rnn: after each update, write the recurrent states the current network computes "
        "over each sampled window back into replay, so later windows start from fresher stored states "
        "(R2D2's stored-state staleness; Kapturowski et al. 2019).",
    )
    insert_td_priorities: bool = Field(
        False,
        description="Prioritized replay: the learner scores data new in replay with its current networks and "
        "sets each step's priority to its |TD| (the original's use_add_with_td), instead of leaving new data at "
        "the table's maximum priority; one forward pass over the new windows per update.",
    )
    compute_dtype: Literal["float32", "bfloat16", "auto"] = Field(
        "float32",
        description="dtype of the hidden layers' matmuls in updates (torch.autocast); output layers, "
        "parameters, optimizer states and losses stay float32. bfloat16 pays on CPUs with AVX512-BF16/AMX; "
        "auto picks it where the hardware has native bfloat16 (those CPUs, CUDA GPUs that support it).",
    )

    @model_validator(mode="after")
    def _check_ensemble(self) -> SacConfig:
        if self.ensemble_q_sample > self.ensemble_q_num:
            raise ValueError("ensemble_q_sample must be <= ensemble_q_num")
        if self.rnd_normalize and not (self.use_rnd and self.rnd_strength > 0):
            raise ValueError("rnd_normalize scales RND's novelty reward: it needs use_rnd: true and rnd_strength > 0")
        if (self.rnd_choice_steps or self.rnd_choice_until_return is not None) and not self.use_rnd:
            raise ValueError("rnd_choice_steps and rnd_choice_until_return end RND's action choice: they need use_rnd")
        if self.burn_in_step and not self.use_rnn:
            raise ValueError("burn_in_step > 0 needs use_rnn: true (burn-in warms up a recurrent state)")
        return self


class NNConfig(Section):
    hidden_units: list[int] = Field(default_factory=lambda: [256, 256], min_length=1)
    activation: Literal["relu", "tanh", "elu", "silu"] = "relu"
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    conv_features: int | None = Field(
        50, ge=1, description="Width of each image encoder's Linear+LayerNorm+tanh head; null = raw conv features."
    )
    rnn_type: Literal["gru", "lstm"] = Field("gru", description="Cell of the recurrent representation (use_rnn).")
    rnn_units: int = Field(64, ge=1, description="Hidden size of the recurrent representation.")
    noisy_q: bool = Field(False, description="Factorised-Gaussian noisy layers in every Q layer.")
    noisy_policy: bool = Field(False, description="A factorised-Gaussian noisy output layer in the policies.")
    noisy_sigma0: float = Field(0.5, gt=0.0, description="Initial noise scale sigma0 of noisy layers (1706.10295).")
    critic_only: list[str] = Field(
        default_factory=list, description="Sensors only the critic sees (privileged state, asymmetric critic)."
    )


class ActorConfig(Section):
    chunk_length: int = Field(64, ge=1, description="Steps per trajectory chunk sent to replay.")
    inserts_in_flight: int = Field(
        1,
        ge=1,
        description="Distributed actors: insert requests on their way to the replay while the actor steps on "
        "(at least; on a link whose round trip is longer than filling a request, up to 8, ds/actor/sink.py). "
        "With chunks_per_insert, bounds what an actor holds when the replay holds it back: "
        "(inserts_in_flight + 1) * chunks_per_insert chunks, which is how stale its data can get. 1: Pendulum "
        "through local --actors 2 reached -200 in a median 2,056 env steps on seeds 0-4 against 2,784 with 2, at "
        "the same actor throughput (README, Measured results).",
    )
    chunks_per_insert: int | None = Field(
        None,
        ge=1,
        description="Distributed actors: the most chunks one insert request carries; null = n_agents (one "
        "chunk per env). Larger requests are cheaper for the replay, smaller ones keep data fresher.",
    )
    random_steps: int = Field(0, ge=0, description="Uniform random actions for the first N env steps.")
    update_policy_mode: bool = Field(
        True,
        description="Distributed actors act with the learner's published weights (true) or ask the "
        "learner for every action over gRPC (false).",
    )
    noise_increasing_rate: float = Field(
        0.0, ge=0.0, description="Distributed actor i explores with extra noise min(rate * i, noise_max)."
    )
    noise_max: float = Field(
        0.1, ge=0.0, le=MAX_EXPLORATION_NOISE, description="Ceiling of the per-actor exploration noise."
    )


class EvalConfig(Section):
    eval_per_step: int = Field(5000, ge=0, description="Evaluate every N env steps; 0 = never.")
    eval_episodes: int = Field(10, ge=1, description="Deterministic episodes per evaluation.")
    eval_envs: int = Field(5, ge=1, description="Parallel evaluation envs (separate from training envs).")


class NetConfig(Section):
    """Where the distributed roles find each other (main_ds.py); a host of null means this host."""

    evolver_host: str | None = Field(None, description="Evolver address; null = this host.")
    evolver_port: int = Field(61000, ge=0, le=65535)
    learner_host: str | None = Field(None, description="Learner address actors connect to; null = this host.")
    learner_port: int = Field(61001, ge=0, le=65535, description="Learner gRPC port (GetParams, GetAction).")
    lease_s: float = Field(
        15.0,
        gt=0.0,
        description="An actor the learner has not heard from (heartbeat) for this long is dropped and its index "
        "freed; actors renew every min(3 s, lease_s / 3) and register again when dropped.",
    )
    rpc_timeout_s: float = Field(
        10.0,
        gt=0.0,
        description="Deadline of one call from a learner or actor to the replay or learner (plus any wait the call "
        "asks for); a peer that has not answered by then (stopped, stalled) is waited for and retried.",
    )
    replay_host: str | None = Field(None, description="Replay address learners and actors connect to.")
    peer_warn_s: float = Field(
        60.0,
        gt=0.0,
        description="A role waiting this long for a peer (a replay, learner or evolver that does not answer, a "
        "replay the evolver has not paired) logs one WARNING naming it and how to fix it; it goes on waiting.",
    )
    replay_port: int = Field(61002, ge=0, le=65535)
    shared_memory: bool = Field(
        True,
        description="A learner on the replay's host takes its batches through a file in /dev/shm rather than the "
        "socket (ds/replay/shared.py); where the replay cannot open it (another host or container) they come over "
        "gRPC by themselves. false = always over gRPC.",
    )
    params_port: int = Field(
        61003, ge=0, le=65535, description="Learner's ZeroMQ parameter broadcast; 0 = any free port (announced)."
    )
    bind_host: str = Field(
        "127.0.0.1", description="Interface servers listen on; 0.0.0.0 to accept other hosts (--in_k8s)."
    )
    token_file: str | None = Field(
        None,
        description="File holding the run's shared secret (e.g. a mounted Kubernetes Secret); the learner "
        "signs its ZeroMQ parameter stream with it (HMAC-SHA256) and actors drop frames that do not verify. "
        "Every role of a run must name the same secret; null = unsigned. With it every gRPC call must carry a key "
        "derived from it too (ds/net/security.py), except the health service.",
    )
    tls_cert: str | None = Field(
        None,
        description="PEM certificate of this process (--tls_cert), with tls_key: its servers speak TLS and present "
        "it, its clients show it to servers that ask. Its DNS subject alternative names are the roles it may act "
        "as (replay, learner, evolver, actor); clients accept a server only if its certificate names the role "
        "they call. null = plaintext.",
    )
    tls_key: str | None = Field(None, description="PEM private key (unencrypted) of tls_cert (--tls_key).")
    tls_ca: str | None = Field(
        None,
        description="PEM certificate of the CA that signs the run's certificates (--tls_ca): clients trust only "
        "servers it signed; servers with it require a client certificate it signed (mutual TLS) and open each "
        "rpc only to the roles that call it (e.g. a learner's GetWeights to the evolver).",
    )
    health_port: int | None = Field(
        None,
        ge=1,
        le=65535,
        description="A plaintext port, beside the role's own, on which only the gRPC health service answers: for "
        "Kubernetes gRPC probes, which speak neither TLS nor tokens (k8s/components/tls). null = none; health "
        "always answers on the role's port too, without the token.",
    )


class Config(Section):
    base_config: BaseConfig = Field(default_factory=BaseConfig)
    reset_config: dict[str, Any] | None = None
    replay_config: ReplayConfig = Field(default_factory=ReplayConfig)
    sac_config: SacConfig = Field(default_factory=SacConfig)
    nn_config: NNConfig = Field(default_factory=NNConfig)
    actor_config: ActorConfig = Field(default_factory=ActorConfig)
    eval_config: EvalConfig = Field(default_factory=EvalConfig)
    net_config: NetConfig = Field(default_factory=NetConfig)
    random_params: dict[str, dict[str, dict[str, Any]]] = Field(
        default_factory=dict,
        description="Hyper-parameters the evolver samples per learner, as {section: {key: spec}} with spec "
        "{in: [...]}, {truncated: [lo, hi]}, {std: s} or {std: s, truncated: [lo, hi]} "
        "(algorithm/config/random_params.py); main.py draws them once for a new run, from its seed, and records "
        "the values in the run's config.yaml.",
    )

    @field_validator("random_params", mode="before")
    @classmethod
    def _empty_random_params(cls, value: Any) -> Any:
        return {} if value is None else value  # a bare `random_params:` in YAML reads as null

    @model_validator(mode="after")
    def _check_random_params(self) -> Config:
        parse_random_params(self.random_params, self)  # raises ParamSpecError naming the key path
        return self

    @model_validator(mode="after")
    def _anneal_over_the_run(self) -> Config:
        """``sac_config.learning_rate_anneal_updates: null`` becomes the run's number of updates, so a
        schedule set for a task still ends with the run when ``base_config.max_step`` is overridden."""
        sac = self.sac_config
        if sac.learning_rate_final is None or sac.learning_rate_anneal_updates is not None:
            return self
        if self.base_config.max_step < 0:
            raise ValueError(
                "sac_config.learning_rate_anneal_updates is null (anneal over the run) but base_config.max_step is "
                "-1 (the run has no end): set learning_rate_anneal_updates to a number of updates"
            )
        sac.learning_rate_anneal_updates = self._run_updates()
        return self

    def _run_updates(self) -> int:
        """The run's number of updates: updates per env step over the env steps after the replay's warm-up."""
        base, replay = self.base_config, self.replay_config
        return max(1, round(replay.updates_per_step * (base.max_step - replay.min_size_to_sample)))

    def derived_keys(self) -> set[str]:
        """Dotted keys whose value is the one this config derives from its other keys (a null in the file
        filled in by a validator), so a copy with other values (``apply_params``: the evolver's learners,
        ``main.py``'s draw) derives them again. Read from the values alone: an explicit anneal equal to the
        run's number of updates counts as derived, the same schedule under another name."""
        sac = self.sac_config
        spans_the_run = (
            sac.learning_rate_final is not None
            and self.base_config.max_step >= 0
            and sac.learning_rate_anneal_updates == self._run_updates()
        )
        return {"sac_config.learning_rate_anneal_updates"} if spans_the_run else set()

    @model_validator(mode="after")
    def _check_munchausen_schedule(self) -> Config:
        sac = self.sac_config
        if sac.munchausen_scale_start is not None and (sac.learning_rate_final is None or sac.munchausen_scale == 0):
            raise ValueError(
                "sac_config.munchausen_scale_start moves the Munchausen weight to munchausen_scale on the step "
                "size's schedule: it needs sac_config.learning_rate_final set and munchausen_scale > 0 (they are "
                f"{sac.learning_rate_final} and {sac.munchausen_scale})"
            )
        return self

    @model_validator(mode="after")
    def _check_insert_td_priorities(self) -> Config:
        if self.sac_config.insert_td_priorities and self.replay_config.alpha == 0:
            raise ValueError(
                "sac_config.insert_td_priorities scores new data for prioritized replay, but replay_config.alpha "
                "is 0 (uniform sampling ignores priorities): set replay_config.alpha > 0 or the option to false"
            )
        return self

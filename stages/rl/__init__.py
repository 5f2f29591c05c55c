"""rl: the sft stage's policy fine-tuned by PPO inside the action world model (or, for
``reward: rule``, inside the simulator); or, with ``algorithm: filtered_bc``, re-cloned on the
demonstrations plus its own successful episodes there (``stages.rl.filtered_bc``).

The world model is the environment (``WorldModelVecEnv``) and, for ``reward: wm``, also the reward:
alpha * sparse (its done head >= theta_sps) + beta * dense (by default LPIPS to the episode's first
frame minus LPIPS to the goal frame the goals stage made; the paper's similarity to the goal with
``dense: similarity``). Baselines share everything but the reward: ``rule`` trains in
ManiSkill on the task's hand-written dense reward; ``embedding`` (iVideoGPT-style) and ``proxy``
(DiWA-style) are reward models fitted to that rule reward. Multi-scene: every training
environment (task x scene) of the SFT policy's tasks is sampled at every reset; multi-task: the
sft stage's ``tasks`` lists several tasks and the instruction tells the policy which.

Inputs:
    collect -- episodes (demonstrations, initial states, rule-reward labels), scene catalog
    tokenize -- token store and tokenizer (the observation function)
    train_wm -- the action world model (with its proprioception head), its split, text embeddings
    wm_play -- whether that model was fine-tuned on the SFT policy's play, and the weights if so
    (``stages.wm_play.action_world_model``): the model everything here imagines in; not read with
    reward ``rule`` (``unread_needs``: PPO runs in the simulator, diagnostics imagine in train_wm's);
    train_wm and goals are not read either by a ``rule`` run with ``diagnostics: none`` and
    ``precision_envs: 0`` (``reads_world_model``): its IND training episodes are then tokenize's
    split, its instruction embeddings the sft artifact's
    goals -- one goal frame per environment
    sft -- the behaviour-cloned policy PPO starts from, its tasks and frame skip (``policy.json``)

Outputs:
    policy.zip          the PPO policy (stable-baselines3), loaded with ``stages.rl.load_policy``; with
                        filtered_bc its last fit in the same format
    snapshots/          policies at evenly spaced points of training (filtered_bc: after each round's fit)
                        + index.json (timesteps, wall s)
    reward_heads.pt     fitted embedding / proxy heads (when fitted)
    guard.pt            the guard's done-classifier ensemble (``guard``; with ``guard_replay_rounds``
                        the last refit's, ``stages.rl.guard_refit``)
    episodes.json       every training episode: return, length, terminated by done head or truncated,
                        success, the env step it started and ended at, its environment ("<task>/<scene_id>")
                        and task
    success_by_start.json  training success in 10 spans of the start step, over the episodes no
                        unfinished one started before (by end order the short, successful ones come first); ``by_task``:
                        the same in 5 spans per task
    training.png        episode return over env steps; training success by start step
    tensorboard/        episode return / length and PPO update statistics, live (``stages.common.curves``)
    reward_diagnostics.png  each module's reward along held-out successful episodes, IND and OOD
    rl.json             the facts this stage fixes, read by evaluate and the sweep report through
                        ``read_rl_facts``: the reward module, whether success pays the steps left,
                        what ``rule`` pays (``rule_terms``), the algorithm (``ppo`` or ``filtered_bc``),
                        what filtered BC imitates (``fbc_select``), the calibration gate's ratio and the
                        method label key (``method_of``)
    filtered_bc.json    with ``algorithm: filtered_bc``: per round, episodes played, successes, episodes
                        imitated (and how many of them successes), pairs and the fit's held-out loss (``stages.rl.filtered_bc``)
    acceptance.json     with ``accept_episodes``: the acceptance test's SFT and PPO success per task on the
                        validation states, their paired difference and which policy ``policy.zip`` holds
                        (``stages.rl.acceptance``); its episodes in ``acceptance_episodes.jsonl``
    calibration.json    with ``calibration_ratio``: per task, the SFT policy's imagined and real success
                        rates and whether PPO trained on it (``stages.rl.calibration``)
    imagined_bc_policy.zip  with ``imagined_bc_epochs`` (PPO): the SFT policy after behaviour cloning on
                        imagined observations, the policy the gate reads and PPO starts from, in PPO's format
                        (``stages.rl.imagined_bc``; ``scripts/evaluate_sft.py ... --rl <rl>/imagined_bc_policy.zip``)
    imagined.json       per split, the final policy's imagined episodes replayed in ManiSkill: where
                        the done head fired and whether the simulator agreed (``stages.rl.imagined``)
    metrics.json        PPO summary, env steps/s, policy parameter change from SFT, diagnostics
                        (mean Spearman correlation of reward with progress per module and split),
                        imagined-success precision per split with its Wilson interval; with
                        ``guard_replay_rounds``, each refit's replayed precision (``guard/replay/...``)

Key includes:
    this config (reward module and its weights, PPO hyper-parameters, seed) and the keys of
    collect, tokenize, train_wm, wm_play (not for ``rule``), goals and sft.

Toy profile:
    4 world-model envs, a few hundred PPO steps, tiny head fits; ``rule`` uses one simulator env
    and fewer steps.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from stages.rl.rewards import REGISTRY, REWARDS

RL_JSON = "rl.json"
# PPO in the world model (reward env "wm", algorithm ppo) when the config leaves them unset: the demonstration-anchor
# test (docs/RESULTS.md) measured the anchored, gated policy above SFT out of domain over four pre-registered seeds
WM_PPO_CALIBRATION_RATIO = 0.5
WM_PPO_DEMO_BC_BATCHES = 8


class Config(BaseModel):
    """rl stage configuration (defaults sized for the ``small`` profile)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, description="seed of PPO, env sampling and head fitting")
    threads: int = Field(2, ge=1, description="torch CPU threads (ignored on CUDA); in the key because on a CPU the "
                         "count changes every step's floating-point reductions, so the policy PPO ends with "
                         "(docs/rl.md, 'The thread count is part of the result')")
    reward: Literal[REWARDS] = Field("wm", description="reward module (stages.rl.rewards.REGISTRY)")
    # reward `wm`
    alpha: float = Field(5.0, ge=0, description="weight of the sparse done-head reward")
    beta: float = Field(0.02, ge=0, description="weight of the dense reward (``dense``)")
    theta_sps: float = Field(0.5, gt=0, lt=1, description="done-head threshold of the sparse reward")
    dense: Literal["progress", "similarity", "potential"] = Field(
        "progress", description="progress: LPIPS to the episode's first frame - LPIPS to the goal (tracks task "
        "progress, docs/rl.md 'The dense term'); similarity: 1 - LPIPS to the goal (the paper's); potential: "
        "gamma*Phi(s') - Phi(s), Phi = -LPIPS to the goal")
    success_payout: bool = Field(True, description="a success that ends an episode is paid the module's per-step "
                                 "maximum for its step and every step left until truncation (discounted): finishing "
                                 "out-earns lingering next to the goal in every module")
    # guard against exploiting the world model (stages.rl.guard)
    guard: bool = Field(False, description="an ensemble of done classifiers: disagreement is penalised and a "
                        "success needs the ensemble's confirmation")
    guard_heads: int = Field(5, ge=2, description="classifiers in the ensemble")
    guard_coef: float = Field(1.0, ge=0, description="penalty per step = guard_coef * max_step_reward * std of their probabilities")
    guard_steps: int = Field(500, ge=1, description="optimisation steps of the ensemble")
    guard_replay_rounds: int = Field(0, ge=0, description="times during PPO the guard is refitted on the current "
                                     "policy's imagined episodes, labelled by replaying them in ManiSkill "
                                     "(stages/rl/guard_refit.py; needs guard); 0 = never")
    guard_replay_envs: int = Field(64, ge=1, description="IND training environments imagined and replayed per refit")
    # environment
    theta_done: float = Field(0.5, gt=0, lt=1, description="done-head threshold that terminates a WM episode")
    done_persist: int = Field(1, ge=1, description="a world-model episode terminates as a success once the done head "
                              "(and the guard, if on) has stayed at or above theta_done for this many consecutive "
                              "steps; 1: at the first such step. The calibration gate and the imagined-success check "
                              "count imagined successes the same way")
    max_episode_steps: int = Field(75, ge=1, description="truncation horizon in world-model steps (= policy steps; "
                                   "planner demos take ~100-280 control steps = 25-70 steps at frame_skip 4)")
    branch_horizon: int = Field(0, ge=0, description="0: world-model episodes start at the first frames of IND "
                                "training episodes and run max_episode_steps; > 0: they start at any frame of those "
                                "episodes before its success (a state the data reached) and are truncated after this "
                                "many steps, PPO bootstrapping the value there (short branched rollouts: the "
                                "imagination stays near real states; world-model rewards only)")
    calibration_ratio: float | None = Field(
        None, ge=0, lt=1, description="0 = off; r > 0: PPO trains in the world model only on the tasks where the SFT "
        "policy's imagined success rate lies within [r, 1/r] x its real rate in wm_play's play "
        "(stages/rl/calibration.py; world-model rewards only); unset: 0.5 for PPO with a world-model reward, else 0 "
        "(the demonstration-anchor test, docs/RESULTS.md)")
    calibration_starts: int = Field(32, ge=1, description="IND training starts per task the calibration gate imagines from")
    imagined_bc_epochs: int = Field(0, ge=0, description="0 = off; n > 0: before the calibration gate and PPO, n epochs "
                                    "of the sft stage's loss on its training demonstrations plus their imagined twins "
                                    "(each demonstration imagined under its own actions, restarted from the real frame "
                                    "every imagined_bc_horizon steps: stages/rl/imagined_bc.py), so the policy acts on "
                                    "the world model's frames as on the simulator's (world-model rewards only)")
    imagined_bc_horizon: int = Field(8, ge=1, description="imagined BC: steps imagined from a real frame before the next "
                                     "restart (32 made the adapted policy itself worse in ManiSkill: docs/rl.md)")
    imagined_bc_lr: float = Field(3e-4, gt=0, description="imagined BC: peak AdamW learning rate (cosine decay to 0)")
    num_envs: int = Field(16, ge=1, description="world-model environments stepped as one batch")
    wm_dtype: Literal["fp32", "bf16", "auto"] = Field(
        "auto", description="the world-model env's step, frame decoding and LPIPS reward convolutions: auto = bf16 on CUDA and on a CPU that runs "
        "bf16 matmuls >= 1.5x faster than fp32 (measured at start), else fp32 (stages.common.precision; same "
        "token accuracy as fp32 on held-out rollouts, benchmarks/wm_precision.py)")
    sim_envs: int = Field(2, ge=1, description="simulator environments for reward: rule")
    rule_terms: Literal["dense", "success"] = Field(
        "success", description="what reward: rule pays (other rewards ignore it); success: success alone, 0 on "
        "every other step (stages/rl/success_only.py); dense: the task's dense reward (reach, grasp, near the "
        "target) and success. success lifted PPO in ManiSkill above SFT in domain over 3 seeds where dense did not "
        "(docs/RESULTS.md)")
    algorithm: Literal["ppo", "filtered_bc"] = Field(
        "ppo", description="ppo: PPO from the SFT policy; filtered_bc: the SFT policy plays total_timesteps steps with "
        "its own action noise, the episodes the environment calls successes join the demonstrations and the sft "
        "recipe is rerun on them (stages/rl/filtered_bc.py; reward rule or wm)")
    fbc_epochs: int = Field(100, ge=1, description="filtered_bc: epochs of the sft recipe, kept at the last one")
    fbc_rounds: int = Field(1, ge=1, description="filtered_bc: rounds of play and fit, the budget split evenly; each "
                            "round's player is the previous round's fit")
    fbc_select: Literal["success", "random", "none"] = Field(
        "success", description="filtered_bc: which played episodes are imitated. success: those the environment calls "
        "successes; random (a control): episodes drawn at random whatever their outcome, as many steps as the "
        "round's successes have, so the fit sees as much own data without the environment's selection; none (a "
        "control): no played episode, the refit on the demonstrations alone, so what the refit itself does is seen")
    # PPO
    total_timesteps: int = Field(20000, ge=1, description="environment steps (PPO's; filtered_bc's play)")
    n_steps: int = Field(64, ge=2, description="rollout length per env per PPO update")
    batch_size: int = Field(256, ge=2, description="PPO minibatch size")
    n_epochs: int = Field(4, ge=1, description="PPO epochs per update")
    learning_rate: float = Field(3e-5, gt=0, description="the actor's Adam step size (3e-4 collapsed the SFT policy "
                                 "in ManiSkill within 3k steps: docs/rl.md)")
    critic_lr_scale: float = Field(10.0, gt=0, description="the critic's learning rate = learning_rate * this")
    gamma: float = Field(0.99, gt=0, le=1)
    clip_range: float = Field(0.2, gt=0)
    ent_coef: float = Field(0.0, ge=0)
    normalize_reward: bool = Field(True, description="scale rewards by a running std of the discounted return "
                                   "(SB3 VecNormalize, rewards only)")
    target_kl: float | None = Field(0.03, gt=0, description="stop an update's epochs once the approximate KL to the "
                                    "rollout policy exceeds 1.5x this (SB3); null = never")
    value_warmup_updates: int = Field(2, ge=0, description="first PPO updates that train the critic only (the "
                                      "policy stays SFT's while the value function learns its returns)")
    freeze_actor_features: bool = Field(False, description="PPO leaves the actor's feature extractor (the CNN over "
                                        "the latent, the proprioception and instruction layers) at SFT's weights; only "
                                        "the actor's MLP, action head and noise adapt (inside the world model the "
                                        "latents are imagined, unlike the real ones evaluation feeds it)")
    noise_scale: float = Field(1.0, gt=0, description="PPO's initial action std = this x the SFT policy's (sft.noise_scale "
                               "x SFT's held-out residual std); below 1 the sampled actions PPO trains on come closer "
                               "to the deterministic ones evaluation runs")
    kl_coef: float = Field(0.0, ge=0, description="after each update, a pass minimising kl_coef * KL(SFT || policy) "
                           "over the rollout (0 = off)")
    demo_bc_batches: int | None = Field(
        None, ge=0, description="after each PPO update, minibatches of behaviour cloning on the SFT stage's training "
        "demonstrations (its own loss; stages.rl.demo_bc; 0 = off): an anchor on the demonstrations' states, after "
        "DAPG; unset: 8 for PPO with a world-model reward, else 0 (the demonstration-anchor test, docs/RESULTS.md)")
    demo_bc_coef: float = Field(1.0, gt=0, description="weight of the demonstration anchor's loss")
    self_imitation_batches: int = Field(8, ge=0, description="after each PPO update, minibatches of self-imitation on "
                                        "the policy's own successful episodes (stages.rl.self_imitation; 0 = off; "
                                        "8 lifted PPO in ManiSkill above SFT in domain: docs/RESULTS.md)")
    self_imitation_weight: Literal["advantage", "success"] = Field(
        "advantage", description="advantage: -log pi * max(R - V, 0) plus the critic's term (SIL); success: every step "
        "of a successful episode weighs 1 (behaviour cloning on the policy's own successes)")
    self_imitation_capacity: int = Field(10000, ge=1, description="steps of successful episodes kept for self-imitation")
    accept_episodes: int = Field(0, ge=0, description="0 = off; n > 0: after PPO the SFT and the PPO policy each run n "
                                 "deterministic episodes per task in ManiSkill from the same IND validation states, and "
                                 "PPO's policy is kept only if its success beats SFT's by more than accept_margin, else "
                                 "policy.zip holds SFT's weights (stages/rl/acceptance.py; simulator episodes, also for "
                                 "world-model rewards)")
    accept_margin: float = Field(0.0, ge=-1, le=1, description="the paired success difference (PPO minus SFT) PPO must "
                                 "exceed in the acceptance test; 1 = never keep PPO")
    snapshots: int = Field(4, ge=0, description="policy checkpoints spread over training (success vs time)")
    precision_envs: int = Field(48, ge=0, description="environments per split (IND, OOD) whose imagined episodes of "
                                "the final policy are replayed in ManiSkill (imagined-success precision; 0 = skip; "
                                "16 gave 2-6 imagined successes per split, too few to read)")
    # learned rewards and diagnostics
    head_episodes: int = Field(200, ge=1, description="IND training episodes the embedding / proxy heads are fitted on")
    head_steps: int = Field(1000, ge=1, description="optimisation steps of each head")
    head_lr: float = Field(1e-3, gt=0)
    diagnostics_episodes: int = Field(16, ge=1, description="held-out successful episodes per split for diagnostics")
    diagnostics: Literal["all", "selected", "none"] = Field(
        "all", description="diagnose every reward module, only the selected one, or none; with none, reward rule and "
        "precision_envs 0 the run reads no world model and no goals (unread_needs: train_wm, goals)")

    @model_validator(mode="before")
    @classmethod
    def _world_model_ppo_defaults(cls, data):
        """Fill the unset ``calibration_ratio`` and ``demo_bc_batches``: PPO in the world model gated (0.5) and
        anchored (8), everything else neither. Filled before validation, so the key holds the value used."""
        if not isinstance(data, dict):
            return data
        reward = data.get("reward", cls.model_fields["reward"].default)
        algorithm = data.get("algorithm", cls.model_fields["algorithm"].default)
        world_model_ppo = reward in REWARDS and REGISTRY[reward].env == "wm" and algorithm == "ppo"
        filled = dict(data)
        for key, on in (("calibration_ratio", WM_PPO_CALIBRATION_RATIO), ("demo_bc_batches", WM_PPO_DEMO_BC_BATCHES)):
            if filled.get(key) is None:
                filled[key] = on if world_model_ppo else type(on)(0)
        return filled

    @model_validator(mode="after")
    def _guard_replay_needs_guard(self) -> "Config":
        if self.guard_replay_rounds and not self.guard:
            raise ValueError(f"guard_replay_rounds={self.guard_replay_rounds} refits the guard, but guard is false: "
                             "set rl.guard=true as well")
        return self

    @model_validator(mode="after")
    def _branches_need_the_world_model(self) -> "Config":
        if self.branch_horizon and REGISTRY[self.reward].env != "wm":
            raise ValueError(f"branch_horizon={self.branch_horizon} starts world-model episodes mid-way, but reward "
                             f"{self.reward!r} trains in the simulator, which starts only from resets; set it to 0")
        return self

    @model_validator(mode="after")
    def _imagined_bc_needs_the_world_model(self) -> "Config":
        if self.imagined_bc_epochs and REGISTRY[self.reward].env != "wm":
            raise ValueError(f"imagined_bc_epochs={self.imagined_bc_epochs} teaches the policy the world model's frames, "
                             f"but reward {self.reward!r} trains in the simulator; set it to 0")
        return self

    @model_validator(mode="after")
    def _calibration_needs_the_world_model(self) -> "Config":
        if self.calibration_ratio and REGISTRY[self.reward].env != "wm":
            raise ValueError(f"calibration_ratio={self.calibration_ratio} gates the tasks PPO trains on in the world "
                             f"model, but reward {self.reward!r} trains in the simulator; set it to 0")
        return self

    @model_validator(mode="after")
    def _filtered_bc_success(self) -> "Config":
        if self.algorithm == "filtered_bc" and self.reward not in ("rule", "wm"):
            raise ValueError(f"algorithm filtered_bc imitates the episodes the environment calls successes (the "
                             f"simulator's for reward rule, the done head's for wm); reward {self.reward!r} changes "
                             "nothing there: use reward rule or wm")
        if self.algorithm == "filtered_bc" and self.calibration_ratio:
            raise ValueError("calibration_ratio gates the tasks PPO trains on; algorithm filtered_bc plays every "
                             "training environment: set it to 0")
        if self.fbc_select != "success" and self.algorithm != "filtered_bc":
            raise ValueError(f"fbc_select={self.fbc_select!r} chooses what filtered BC imitates, but algorithm is "
                             f"{self.algorithm!r}: set rl.algorithm=filtered_bc or leave fbc_select at success")
        if self.done_persist > 1 and self.reward == "rule":
            raise ValueError(f"done_persist={self.done_persist} holds the world model's done head for several steps; "
                             "reward rule trains in ManiSkill, whose success check has no done head: leave it at 1")
        if self.done_persist > self.max_episode_steps:
            raise ValueError(f"done_persist={self.done_persist} > max_episode_steps={self.max_episode_steps}: an episode "
                             "truncates before the done head can hold that long, so none would end as a success")
        if self.algorithm == "filtered_bc" and self.guard_replay_rounds:
            raise ValueError("guard_replay_rounds refits the guard during PPO; algorithm filtered_bc runs no PPO: set it to 0")
        return self

    @model_validator(mode="after")
    def _return_scales(self) -> "Config":
        # without the payout, success ends the episode and forfeits the per-step reward that lingering
        # keeps earning: 131 of 266 rule episodes of one seed hovered by the object (docs/rl.md, "Success is worth the most")
        if self.success_payout or (self.reward == "rule" and self.rule_terms == "success"):
            return self  # success alone pays nothing for lingering
        if self.reward != "wm":
            raise ValueError(f"reward {self.reward!r} with success_payout false: its per-step reward is positive "
                             "next to the goal, so lingering until truncation out-earns finishing; keep the payout")
        if self.dense != "potential" and self.alpha <= self.beta * self.max_episode_steps:
            raise ValueError(
                f"alpha ({self.alpha}) <= beta * max_episode_steps ({self.beta * self.max_episode_steps:g}): "
                "an episode that lingers near the goal would earn more dense reward than one that finishes; "
                "keep success_payout, raise alpha, lower beta, or use dense: potential")
        return self


def run(ctx) -> None:
    from stages.rl.inputs import RLInputs
    from stages.rl.train import train

    cfg: Config = ctx.config
    if ctx.device == "cpu":  # the config's count, not the cores the executor gave this node: the same key
        torch.set_num_threads(cfg.threads)  # then gives the same weights in a single run and in a sweep wave
    inputs = RLInputs.load(ctx, cfg)
    metrics = train(ctx, cfg, inputs)
    facts = {"reward": cfg.reward, "success_payout": cfg.success_payout,
             "rule_terms": cfg.rule_terms if cfg.reward == "rule" else None, "algorithm": cfg.algorithm,
             "method": method_of(cfg.reward, cfg.rule_terms, cfg.algorithm, cfg.fbc_select, cfg.calibration_ratio,
                                 cfg.branch_horizon, cfg.imagined_bc_epochs, cfg.done_persist),
             "fbc_select": cfg.fbc_select, "calibration_ratio": cfg.calibration_ratio, "done_persist": cfg.done_persist}
    (ctx.out / RL_JSON).write_text(json.dumps(facts) + "\n")
    ctx.write_metrics(metrics)


def reads_world_model(cfg: Config) -> bool:
    """Whether a run reads train_wm's world model and the goals: it trains in the world model, diagnoses a
    reward module, imagines its final policy (``precision_envs``) or fits a guard on its hidden states.
    A ``rule`` run with ``diagnostics: none``, ``precision_envs: 0`` and no guard plays only in ManiSkill."""
    return REGISTRY[cfg.reward].env == "wm" or cfg.diagnostics != "none" or cfg.precision_envs > 0 or cfg.guard


def unread_needs(cfg: Config) -> list[str]:
    """The declared inputs this config does not read (the engine's ``Project.used_needs``): PPO in the
    simulator (``rule``) reads no play-tuned world model (its reward diagnostics imagine in
    train_wm's), so a ``rule`` run neither waits for wm_play nor changes key with it; one that reads no
    world model at all (``reads_world_model``) neither waits for train_wm and goals."""
    unread = ["wm_play"] if cfg.reward == "rule" else []
    return unread if reads_world_model(cfg) else [*unread, "train_wm", "goals"]


def method_of(reward: str, rule_terms: str, algorithm: str = "ppo", fbc_select: str = "success",
              calibration_ratio: float = 0.0, branch_horizon: int = 0, imagined_bc_epochs: int = 0,
              done_persist: int = 1) -> str:
    """The method a run stands for in tables: the reward module, with ``rule`` split by what it pays
    (``rule``: success alone, the default; ``rule_dense``: the task's dense reward); filtered BC
    (``algorithm: filtered_bc``) is ``<reward>_fbc`` (its reward only names the environment and its success),
    its control that imitates random episodes (``fbc_select: random``) ``<reward>_fbc_random`` and the one that
    imitates none (``fbc_select: none``, the refit alone) ``<reward>_fbc_none``. PPO in
    the world model carries a suffix per option that changes what it trains on, in this order: ``_gated``
    (the calibration gate, ``calibration_ratio`` > 0), ``_branched`` (episodes from mid-demonstration
    frames, ``branch_horizon`` > 0), ``_ibc`` (imagined behaviour cloning first, ``imagined_bc_epochs`` > 0),
    so a sweep over any of them keeps its arms apart (``wm_gated_ibc``). Either algorithm in the world model
    ends with ``_persist`` when a success must hold for several steps (``done_persist`` > 1): ``wm_fbc_persist``."""
    persist = "_persist" if done_persist > 1 else ""
    if algorithm == "filtered_bc":
        return f"{reward}_fbc" + ("" if fbc_select == "success" else f"_{fbc_select}") + persist
    base = "rule_dense" if reward == "rule" and rule_terms == "dense" else reward
    return (base + ("_gated" if calibration_ratio > 0 else "") + ("_branched" if branch_horizon > 0 else "")
            + ("_ibc" if imagined_bc_epochs > 0 else "") + persist)


def read_rl_facts(rl_dir: str | Path) -> dict:
    """The rl artifact's ``rl.json`` (reward module, success payout, rule terms, method), with a clear error."""
    path = Path(rl_dir) / RL_JSON
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: is {rl_dir} a committed rl artifact of this version?")
    facts = json.loads(path.read_text())
    # rl.json without them predates rule_terms (rl re-keyed since): rule paid the task's dense reward
    facts.setdefault("method", method_of(facts["reward"], facts.get("rule_terms") or "dense"))
    return facts


__all__ = ["Config", "run", "unread_needs", "reads_world_model", "read_rl_facts", "method_of", "REWARDS", "RL_JSON"]

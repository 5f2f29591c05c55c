"""The simulator as an RL environment with the SAME observation function as the world model.

Used by the ``rule`` baseline (PPO directly in ManiSkill with the task's hand-written dense reward,
the paper's "RL w. ManiSkill" row) and by evaluation. One env step repeats the policy's action for
``action_repeat`` control steps (the world model's frame skip, ``stages.common.frame_skip``), so a
policy step means the same in the simulator as in the world model; the reward is the task's
(state-based) normalised dense reward after the last of them, ``max_steps`` counts policy steps.
Only the last control step of a policy step renders the cameras (unless ``keep_frames``): the others
are never observed (a policy step of 4 control steps: 64 ms rendering each, 32 ms rendering the
last). With ``payout_gamma`` set, a successful step is paid the rule reward's maximum (1) for
itself and each step left (``stages.common.returns.success_return``). Each env samples one of its
assigned (task, scene) environments at reset; simulator instances are created lazily and cached
(building one costs seconds), at most ``cache_size`` per env.

Every reset rebuilds the env's scene (ManiSkill's ``reconfiguration_freq=1``), so an episode does not
depend on what the simulator ran before it. Resetting the poses and velocities in a scene that has
already simulated is not enough: the physics engine keeps state across such a reset (which state was
not examined), and the same actions from the same seed then went elsewhere after other episodes
(6.5 cm apart on a scripted push, 3 cm on a noisy pick-and-place plan; 4 of 24 noisy plans diverged;
docs/RESULTS.md notebook, 2026-12-05). With ``freeze_heap_once`` the rebuild costs no measurable time:
``reset`` took 72-101 ms a call with it and 76-85 ms without (8 toy evaluation episodes under
cProfile, twice each, 2-core EPYC; docs/evaluate.md). With the rebuild an
episode's trajectory is the same bit for bit whatever ran before it, so evaluation's outcomes do not
depend on how its jobs were spread over workers or resumed (``tests/common/test_sim_history.py``).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from stages.common.action_space import executed
from stages.common.proprio import proprio_from_sim_state
from stages.common.returns import success_return
from stages.sft.observation import ObservationFn, index_obs

RULE_MAX_STEP_REWARD = 1.0  # the task's dense reward is normalised to [0, 1], 1 exactly at success


@dataclass(frozen=True)
class SimSpec:
    task: str
    scene: dict  # Scene.to_dict() of the collect catalog
    instruction: str = ""  # empty: the env's own instruction for the scene
    env_index: int = -1  # row in the goals artifact, -1 if none

    @property
    def key(self) -> str:
        return f"{self.task}/{self.scene['scene_id']}"


_KEPT_RENDERERS: dict[str, object] = {}  # render device name -> a SAPIEN render system held until the process ends


def keep_renderer(env: gym.Env) -> None:
    """Hold one SAPIEN render system on ``env``'s render device for the rest of the process.

    SAPIEN frees its renderer's resources when the process's last render system goes (its last env
    closed), and the next env's first picture regenerates them: 11-15 s on the software Vulkan
    driver, nearly all of it the renderer's BRDF lookup table (docs/collect.md), against ~0.2 s while
    one is held (the imagined-success check builds a simulator per split, one after the other). The
    table is the same either way, and so are the pixels (tests/rl/test_same_observation.py).
    """
    device = env.unwrapped.backend.render_device  # None: rendering is off, nothing to hold
    if device is None or str(device) in _KEPT_RENDERERS:
        return
    import sapien.render

    _KEPT_RENDERERS[str(device)] = sapien.render.RenderSystem(device)


def freeze_heap_once() -> None:
    """Before a process's first simulator: collect garbage once and move every live object into the
    collector's permanent generation (``gc.freeze``), once per process.

    ManiSkill calls ``gc.collect()`` whenever it builds or clears a scene (twice per env built); in
    a process holding torch, the tokenizer and a policy each call walked millions of objects,
    0.26 s (toy evaluate, cProfile: 64 calls, 16.3 s of its 60 s). Frozen objects are skipped by
    later collections (those calls then took 0.09 s); objects made later are collected as before,
    and frozen ones are still freed when their reference count drops to zero: only cyclic garbage
    among what was alive at the freeze stays. ManiSkill's and SAPIEN's modules are imported before
    the freeze (2026-12-05: imported after it, they were most of what each collection walked; in the
    toy evaluation's process, cProfile, a collection took 64 ms with them unfrozen and 1.6 ms frozen,
    and a reset with its scene rebuild 197 ms -> 103 ms).
    """
    global _FROZEN
    if _FROZEN:
        return
    import gc

    from stages.collect.sim import _import_envs

    _import_envs()  # ManiSkill's and SAPIEN's modules: imported after the freeze, every collection walked them
    gc.collect()
    gc.freeze()
    _FROZEN = True


_FROZEN = False


class SimTaskEnv(gym.Env):
    """ManiSkill task env -> {codes, proprio, instruction} observations, rule reward, success = terminated."""

    metadata = {"render_modes": []}

    def __init__(self, specs: list[SimSpec], obs_fn: ObservationFn, *, max_steps: int, image_size: int = 64,
                 robot_mesh: str = "lowpoly", seed: int = 0, cache_size: int = 2, keep_frames: bool = False,
                 action_repeat: int = 1, payout_gamma: float | None = None):
        if not specs:
            raise ValueError("SimTaskEnv needs at least one (task, scene)")
        if action_repeat < 1:
            raise ValueError(f"action_repeat must be >= 1, got {action_repeat}")
        self.action_repeat, self.payout_gamma = action_repeat, payout_gamma
        self.specs, self.obs_fn, self.max_steps = list(specs), obs_fn, max_steps
        self.image_size, self.robot_mesh, self.cache_size = image_size, robot_mesh, cache_size
        self.observation_space = obs_fn.space
        self.action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
        self.rng = np.random.default_rng(seed)
        self._envs: OrderedDict[str, gym.Env] = OrderedDict()
        self.spec_now: SimSpec = self.specs[0]
        self.env: gym.Env | None = None
        self.t = 0
        self.instruction = ""
        self.keep_frames = keep_frames
        self.frames: list[tuple[np.ndarray, np.ndarray]] = []  # (third, wrist) of every control step when kept
        self.first_tokens = None  # (1, h, w) the episode's first frame's tokens (the policy may observe them)
        self.tokens = None  # (1, h, w) the last observed frame's tokens

    def _env_for(self, spec: SimSpec) -> gym.Env:
        from stages.collect.sim import make_task_env

        if spec.key in self._envs:
            self._envs.move_to_end(spec.key)
            return self._envs[spec.key]
        while len(self._envs) >= self.cache_size:
            _, old = self._envs.popitem(last=False)
            old.close()
        freeze_heap_once()
        env = make_task_env(spec.task, spec.scene, image_size=self.image_size, robot_mesh=self.robot_mesh,
                            reconfiguration_freq=1)  # every reset rebuilds the physics scene: see the module docstring
        keep_renderer(env)
        self._envs[spec.key] = env
        return env

    def _observe(self, raw: dict, first: bool = False) -> dict[str, np.ndarray]:
        """The policy's observation of the rendered views; ``first``: they are the episode's first frame."""
        tokens = self.obs_fn.tok.encode(raw["third"][None], raw["wrist"][None]).cpu()  # (1, h, w)
        self.tokens = tokens
        if first:
            self.first_tokens = tokens
        obs = self.obs_fn.from_tokens(tokens, proprio_from_sim_state(raw["state"]), [self.instruction],
                                      first=self.first_tokens)
        return index_obs(obs, 0)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.rng = np.random.default_rng(seed)
        spec = (options or {}).get("spec") or self.specs[int(self.rng.integers(len(self.specs)))]
        self.spec_now = spec
        self.env = self._env_for(spec)
        self.instruction = spec.instruction or self.env.instruction
        raw, info = self.env.reset(seed=int(self.rng.integers(2**31 - 1)))
        self.t = 0
        self.frames = [(raw["third"], raw["wrist"])] if self.keep_frames else []
        return self._observe(raw, first=True), {"success": bool(info["success"]), "env": spec.key}

    def step(self, action):
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape != (7,) or not np.isfinite(a).all():
            raise ValueError(f"expected a finite (7,) action, got {a!r}")
        a = executed(a)
        for r in range(self.action_repeat):
            if r < self.action_repeat - 1 and not self.keep_frames:
                if not self._unobserved_control_step(a):
                    continue  # an intermediate repeat: nobody sees its frames, so none are rendered
                raw, reward, env_truncated, info = self._observe_current(a)  # success mid-repeat: observe it, end
                break
            raw, reward, _, env_truncated, info = self.env.step(a)
            if self.keep_frames:
                self.frames.append((raw["third"], raw["wrist"]))
            if info["success"] or env_truncated:
                break
        self.t += 1
        success = bool(info["success"])
        truncated = (self.t >= self.max_steps or bool(env_truncated)) and not success
        if success and self.payout_gamma is not None:
            reward = float(success_return(RULE_MAX_STEP_REWARD, self.max_steps - self.t, self.payout_gamma))
        return self._observe(raw), float(reward), success, truncated, {"success": success, "env": self.spec_now.key}

    def _unobserved_control_step(self, a: np.ndarray) -> bool:
        """One control step without rendering; returns the task's success flag.

        ManiSkill's ``step`` renders both cameras for its observation (8 of its 16 ms on this machine).
        The first ``action_repeat - 1`` control steps of a policy
        step are never observed, so they run what ``step`` runs minus ``get_obs`` / ``get_reward``: the
        controller and physics (``_step_action``), the step counter, the task's evaluation. ManiSkill's
        own API (pinned version); ``tests/rl/test_same_observation.py`` checks the result equals full steps.
        """
        base = self.env.unwrapped
        base._step_action(a[None])
        base._elapsed_steps += 1
        return bool(base.get_info()["success"].reshape(-1)[0])

    def _observe_current(self, a: np.ndarray):
        """(raw obs, reward, truncated, info) of the current state, as the wrapped env's ``step`` returns them."""
        import torch

        base = self.env.unwrapped
        info = base.get_info()
        obs = base.get_obs(info, unflattened=True)
        reward = base.get_reward(obs=obs, action=torch.as_tensor(a[None]), info=info)
        return self.env._obs(obs), float(reward.reshape(-1)[0]), False, self.env._info(info)

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()


def sim_over(collect_dir, obs_fn: ObservationFn, envs: list, *, max_steps: int, frame_skip: int, seed: int):
    """(a ``SimTaskEnv`` over ``envs`` (``stages.goals.environments.Environment``), rendering and
    controlling as collect did, their ``SimSpec`` in order)."""
    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts

    scenes = read_scenes_json(Path(collect_dir) / "scenes.json")
    facts = read_sim_facts(collect_dir)
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction) for e in envs]
    sim = SimTaskEnv(specs, obs_fn, max_steps=max_steps, action_repeat=frame_skip, image_size=facts.image_size,
                     robot_mesh=facts.robot_mesh, seed=seed)
    return sim, specs

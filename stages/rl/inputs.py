"""Everything the rl stage reads from its inputs, loaded once."""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from stages.common.frame_skip import compose_actions, frame_indices, per_step
from stages.common.proprio import proprio_from_state
from stages.goals.environments import Environment, list_environments
from stages.rl.wm_env import Start
from stages.sft.observation import ObservationFn


@dataclass
class RLInputs:
    tok: object  # stages.tokenize.tokenizer.Tokenizer
    store: object  # stages.tokenize.store.TokenStore
    dataset: object  # stages.collect.dataset.Dataset
    meta: dict  # episode_id -> EpisodeMeta
    split: dict  # {"train": [...], "heldout": [...], "ood": [...]} from train_wm (without it: tokenize's, OOD from collect)
    envs: list[Environment]  # every environment, in the goals artifact's order
    goal_index: dict  # env_id -> row in the goals artifact (empty without goals)
    goals: dict | None  # stages.goals.load_goals; None when the run reads no world model (stages.rl.reads_world_model)
    wm: object  # the action world model (stages.train_wm.rollout.WorldModel), fine-tuned by wm_play if it did; or None
    obs_fn: ObservationFn
    device: str
    sft_policy: object  # stages.sft.policy.TaskPolicy, what PPO starts from
    sft_info: dict  # the sft artifact's policy.json (tasks, frame_skip, policy_kwargs)

    @classmethod
    def load(cls, ctx, cfg) -> "RLInputs":
        from stages.collect.dataset import Dataset
        from stages.goals import load_goals
        from stages.rl import unread_needs
        from stages.sft import TEXT_EMBEDDINGS as SFT_TEXT_EMBEDDINGS, read_policy_json
        from stages.sft.policy import POLICY_FILE, load_policy
        from stages.tokenize.store import TokenStore
        from stages.tokenize.tokenizer import load_tokenizer
        from stages.train_wm.rollout import TEXT_EMBEDDINGS, load_world_model
        from stages.wm_play import action_world_model

        sft_info = read_policy_json(ctx.input("sft"))
        tok = load_tokenizer(ctx.input("tokenize"), ctx.device)
        ds = Dataset(ctx.input("collect"))
        envs = list_environments(ctx.input("collect"))
        sft_policy = load_policy(ctx.input("sft") / POLICY_FILE, ctx.device)
        if "train_wm" in unread_needs(cfg):  # ManiSkill only (stages.rl.reads_world_model): no world model, no goals
            tok_split = json.loads((ctx.input("tokenize") / "split.json").read_text())
            split = {"train": tok_split["train"], "heldout": tok_split.get("heldout", []),
                     "ood": [m.episode_id for m in ds.episodes if m.split == "ood"]}
            text = json.loads((ctx.input("sft") / SFT_TEXT_EMBEDDINGS).read_text())
            return cls(tok=tok, store=TokenStore(ctx.input("tokenize")), dataset=ds,
                       meta={m.episode_id: m for m in ds.episodes}, split=split, envs=envs, goal_index={}, goals=None,
                       wm=None, obs_fn=ObservationFn.for_policy(tok, text, sft_info), device=ctx.device, sft_policy=sft_policy,
                       sft_info=sft_info)
        wm_dir = ctx.input("train_wm")
        if "wm_play" not in unread_needs(cfg):
            wm = action_world_model(ctx.input("wm_play"), wm_dir, device=ctx.device)
        else:  # rule reads no play-tuned model (stages.rl.unread_needs): train_wm's
            wm = load_world_model(wm_dir, kind="action", device=ctx.device)
        if int(sft_info["frame_skip"]) != wm.spec.frame_skip:
            raise ValueError(f"sft.frame_skip ({sft_info['frame_skip']}) != train_wm.frame_skip ({wm.spec.frame_skip}): "
                             "a policy step must mean the same number of control steps in both; set them equal")
        if "proprio" in sft_info["observation"] and wm.proprio_head is None:
            raise ValueError(f"the SFT policy observes proprioception but the world model in {wm_dir} has no "
                             "proprioception head (proprio_head.pt); rerun train_wm")
        goals = load_goals(ctx.input("goals"))
        goal_index = {env_id: i for i, env_id in enumerate(goals["env_ids"])}
        missing = [e.env_id for e in envs if e.env_id not in goal_index]
        if missing:
            raise ValueError(f"the goals artifact has no goal for environments {missing[:5]}")
        text = json.loads((wm_dir / TEXT_EMBEDDINGS).read_text())
        return cls(tok=tok, store=TokenStore(ctx.input("tokenize")), dataset=ds,
                   meta={m.episode_id: m for m in ds.episodes},
                   split=json.loads((wm_dir / "split.json").read_text()), envs=envs, goal_index=goal_index,
                   goals=goals, wm=wm, obs_fn=ObservationFn.for_policy(tok, text, sft_info), device=ctx.device,
                   sft_policy=sft_policy, sft_info=sft_info)

    @property
    def tasks(self) -> list[str]:
        """The tasks of the SFT policy, which PPO fine-tunes on."""
        return list(self.sft_info["tasks"])

    @property
    def frame_skip(self) -> int:
        """Control steps per world-model (= policy) step (the SFT policy's; ``load`` checks the world model agrees)."""
        return int(self.sft_info["frame_skip"])

    def tokens(self, episode_id: str) -> np.ndarray:
        """(T'+1, h, w) int64 tokens of an episode's world-model frames (every ``frame_skip``-th frame)."""
        tokens = np.asarray(self.store.episode(episode_id), dtype=np.int64)
        return tokens[frame_indices(len(tokens) - 1, self.frame_skip)]

    def steps(self, episode_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World-model steps of an episode: tokens (T'+1, h, w), composed actions (T', 7), rule reward
        (T',) and the simulator's success flag (T',) after each step."""
        ep = self.dataset.load_states(episode_id)
        n, k = len(ep["action"]), self.frame_skip
        return (self.tokens(episode_id), compose_actions(ep["action"], k),
                per_step(np.asarray(ep["reward"], dtype=np.float32), n, k),
                np.asarray(ep["success"], dtype=bool)[frame_indices(n, k)[1:]])

    def first_proprio(self, episode_id: str) -> np.ndarray:
        """(10,) proprioception of an episode's first frame."""
        ep = self.dataset.load_states(episode_id)
        return proprio_from_state(ep["ee_pose"][:1], ep["qpos"][:1])[0]

    def training_envs(self, tasks: list[str]) -> list[Environment]:
        from stages.common.environments import training_environments

        return training_environments(self.envs, self.split["train"], tasks)

    def starts(self, envs: list[Environment], any_frame: bool = False) -> list[Start]:
        """States world-model episodes start from: the first frames of the training episodes of ``envs``,
        or with ``any_frame`` every world-model frame of them before the first successful one."""
        train = set(self.split["train"])
        ids = [(e, i) for e in envs for i in e.episodes if i in train]
        if not any_frame:
            return [Start(self.goal_index[e.env_id], e.instruction, self.tokens(i)[0], self.first_proprio(i), e.env_id)
                    for e, i in ids]
        return [s for e, i in ids for s in self._starts_before_success(e, i)]

    def _starts_before_success(self, env: Environment, episode_id: str) -> list[Start]:
        ep = self.dataset.load_states(episode_id)
        idx = frame_indices(len(ep["action"]), self.frame_skip)  # (T'+1,) control-step index of each WM frame
        success = np.asarray(ep["success"], dtype=bool)[idx]  # (T'+1,)
        end = int(np.argmax(success)) if success.any() else len(idx)  # frames [0, end) are not yet successful
        if end == 0:
            return []
        tokens = self.tokens(episode_id)  # (T'+1, h, w)
        proprio = proprio_from_state(np.asarray(ep["ee_pose"])[idx[:end]], np.asarray(ep["qpos"])[idx[:end]])  # (end, 10)
        return [Start(self.goal_index[env.env_id], env.instruction, tokens[j], proprio[j], env.env_id) for j in range(end)]

    def goal_frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Decoded goal frames (G, 3, H, W) x 2 in [0, 1], rows as in the goals artifact."""
        return self.tok.decode(torch.as_tensor(self.goals["tokens"].astype(np.int64)))

    def episodes_for(self, ids: list[str], tasks: list[str], successful_only: bool, limit: int, seed: int,
                     kinds: list[str] | None = None) -> list[str]:
        """Up to ``limit`` episode ids from ``ids`` of ``tasks`` (a seeded choice)."""
        pick = [i for i in ids if self.meta[i].task in tasks and (self.meta[i].success or not successful_only)
                and (kinds is None or self.meta[i].kind in kinds)]
        if len(pick) > limit:
            rng = np.random.default_rng(seed)
            pick = [pick[j] for j in sorted(rng.choice(len(pick), size=limit, replace=False))]
        return pick

    def env_of(self, episode_id: str) -> int:
        m = self.meta[episode_id]
        return self.goal_index[f"{m.task}/{m.scene_id}"]

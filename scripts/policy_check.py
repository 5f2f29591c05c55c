"""What scripts/replay_imagined.py and scripts/wm_closed_loop.py both load: the tokenizer, the
observation function, the action world model, a policy, and a simulator over picked environments;
and their shared decoding options."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path


@dataclass
class PolicyCheck:
    tok: object  # stages.tokenize.tokenizer.Tokenizer
    obs_fn: object  # stages.sft.observation.ObservationFn
    wm: object  # stages.train_wm.rollout.WorldModel (the action WM)
    policy: object
    specs: list  # stages.common.sim_env.SimSpec, one per picked environment
    sim: object  # stages.common.sim_env.SimTaskEnv over ``specs`` (close it)


def load_check(collect: Path, tokenize: Path, train_wm: Path, sft: Path, policy_path: Path, *, split: str,
               envs: int, steps: int, keep_frames: bool = False, decode_steps: int | None = None,
               temperature: float | None = None, wm_play: Path | None = None,
               wm_net: Path | None = None) -> PolicyCheck:
    """``envs`` environments of ``split`` (round-robin over the SFT policy's tasks), on CPU.

    decode_steps, temperature: the world model's rollout decoding (None: the train_wm artifact's own).
    wm_play: a wm_play artifact: its fine-tuned weights replace train_wm's (the model rl trained in).
    wm_net: an action world-model checkpoint (e.g. ``scripts/wm_ablation.py --save``) that replaces
    train_wm's network, architecture included; train_wm's proprioception head and decoding stay.
    """
    from stages.collect.catalog import read_scenes_json
    from stages.collect.dataset import read_sim_facts
    from stages.goals.environments import list_environments
    from stages.common.environments import pick_environments
    from stages.common.sim_env import SimSpec, SimTaskEnv
    from stages.sft import TEXT_EMBEDDINGS, read_policy_json
    from stages.sft.observation import ObservationFn
    from stages.sft.policy import load_policy
    from stages.tokenize.tokenizer import load_tokenizer
    from stages.train_wm.rollout import load_world_model

    if wm_net is not None and wm_play is not None:
        raise SystemExit("--wm-net and --wm-play each replace the world model; give one")
    tok = load_tokenizer(tokenize, "cpu")
    obs_fn = ObservationFn.for_policy(tok, json.loads((sft / TEXT_EMBEDDINGS).read_text()), read_policy_json(sft))
    wm = load_world_model(train_wm, "action", "cpu", decode_steps=decode_steps, temperature=temperature)
    if wm_play is not None:
        from stages.wm_play import action_world_model

        wm.net.load_state_dict(action_world_model(wm_play, train_wm).net.state_dict())
    if wm_net is not None:
        from stages.train_wm.rollout import WorldModel, load_net

        wm = WorldModel(load_net(wm_net), wm.decode_steps, wm.temperature, wm._text, wm.proprio_head)
    tasks = read_policy_json(sft)["tasks"]
    scenes, facts = read_scenes_json(collect / "scenes.json"), read_sim_facts(collect)
    picked = pick_environments([e for e in list_environments(collect) if e.split == split and e.task in tasks], envs)
    specs = [SimSpec(e.task, scenes[e.scene_id].to_dict(), e.instruction) for e in picked]
    sim = SimTaskEnv(specs, obs_fn, max_steps=steps, action_repeat=int(wm.spec.frame_skip),
                     image_size=facts.image_size, robot_mesh=facts.robot_mesh, keep_frames=keep_frames)
    return PolicyCheck(tok, obs_fn, wm, load_policy(policy_path, "cpu"), specs, sim)


def add_artifact_args(ap, names=("collect", "tokenize", "train_wm", "sft")) -> None:
    """Positional artifact directories, in pipeline order."""
    for name in names:
        ap.add_argument(name, type=Path, help=f"a committed {name} artifact directory")
    if "train_wm" in names:
        ap.add_argument("--wm-play", type=Path, default=None,
                        help="a committed wm_play artifact: imagine in its fine-tuned action world model, the one "
                             "the rl stage trains in (default: train_wm's as it is)")


def add_wm_net_option(ap) -> None:
    """--wm-net FILE: imagine in another action world-model checkpoint (``load_check``'s ``wm_net``)."""
    ap.add_argument("--wm-net", type=Path, default=None,
                    help="an action world-model checkpoint file (scripts/wm_ablation.py --save) to imagine in "
                         "instead of train_wm's network (its proprioception head and decoding stay)")


def add_decoding_options(ap) -> None:
    """--decode-steps / --temperature: override the world model's rollout decoding."""
    ap.add_argument("--decode-steps", type=int, default=None,
                    help="MaskGIT passes per imagined frame (default: the train_wm artifact's decode_steps)")
    ap.add_argument("--temperature", type=float, default=None,
                    help="token sampling temperature of imagined frames (default: the artifact's, 0 = greedy)")

"""Do false imagined successes show an imagined arm that is not where the actions put it?

The policy check (``stages.rl.imagined``) finds most imagined successes false, and its strips show
the imagined arm taking another path than the replayed arm under the same actions. This probe asks
whether that drift is visible *inside* the world model, i.e. without the simulator, which an rl env
could then use to end or discount a drifted imagined episode:

1. an **arm locator**: a small regressor from one frame's token codes to the TCP position, fitted on
   the real frames of the training episodes of a ``wm_size_probe.py export`` (same tokenizer);
   its error on held-out real frames is printed;
2. the policy check (the SFT policy acting inside the world model, its actions replayed open loop in
   ManiSkill), recording the imagined frames, the imagined proprioception (the proprioception head,
   driven mostly by the actions) and the replayed proprioception;
3. per imagined success, at its imagined done (the mean over the last ``--window`` steps up to it,
   so that one frame's locator error does not decide): the gap between the located TCP of the
   imagined frame and the imagined proprioception's TCP (**observable in the world model**), the gap
   between the located TCP and the replay's real TCP (the drift itself, for reference) and between
   the imagined proprioception and the real TCP, split by whether the replay confirmed the success;
   and the precision had imagined successes with an observable gap above g been vetoed, for a few g.

    PYTHONPATH=. .venv/bin/python scripts/arm_consistency_probe.py <export.pt> <collect> <tokenize> <train_wm> <sft> \\
        [--split ind|ood] [--envs 32] [--steps 75]

<train_wm> is any folder that loads as one (e.g. ``wm_size_probe.py assemble``'s output); the
export must be tokenized with <tokenize>'s tokenizer.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn


class ArmLocator(nn.Module):
    """Token codes of one frame (B, bits, h, w) -> TCP position (B, 3) in metres."""

    def __init__(self, bits: int, grid: tuple[int, int], hidden: int = 256):
        super().__init__()
        self.net = nn.Sequential(nn.Flatten(), nn.Linear(bits * grid[0] * grid[1], hidden), nn.GELU(),
                                 nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, 3))
        self.register_buffer("mean", torch.zeros(3))  # (3,) mean TCP position of the fitted frames, m

    def forward(self, codes: torch.Tensor) -> torch.Tensor:
        return self.net(codes) + self.mean


def frames_and_tcp(episodes, codes_fn) -> tuple[torch.Tensor, torch.Tensor]:
    """(codes (M, bits, h, w), TCP position (M, 3) m) of every frame of ``episodes``."""
    from stages.common.proprio import tcp_position_m

    codes = torch.cat([codes_fn(e.tokens) for e in episodes]).float()
    tcp = torch.from_numpy(np.concatenate([tcp_position_m(e.proprio) for e in episodes])).float()
    return codes, tcp


def fit_locator(locator: ArmLocator, codes: torch.Tensor, tcp: torch.Tensor, steps: int, seed: int) -> dict:
    from stages.train_wm.head_fit import fit_head

    locator.mean.copy_(tcp.mean(0))

    def batch_loss(gen: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, len(codes), (256,), generator=gen)
        return ((locator(codes[idx]) - tcp[idx]) ** 2).sum(1).mean() * 1e4  # squared error in cm^2

    return fit_head(locator, batch_loss, steps=steps, lr=1e-3, seed=seed)


@torch.no_grad()
def locate(locator: ArmLocator, codes: torch.Tensor) -> np.ndarray:
    """(M, 3) located TCP positions in metres."""
    return locator(codes.float()).numpy()


def main() -> None:
    from policy_check import load_check

    from wm_size_probe import load_data

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("export", type=Path, help="a wm_size_probe.py export (its training episodes fit the locator)")
    for name in ("collect", "tokenize", "train_wm", "sft"):
        ap.add_argument(name, type=Path)
    ap.add_argument("--split", choices=["ind", "ood"], default="ind")
    ap.add_argument("--envs", type=int, default=32)
    ap.add_argument("--steps", type=int, default=75)
    ap.add_argument("--theta", type=float, default=0.5)
    ap.add_argument("--locator-steps", type=int, default=3000)
    ap.add_argument("--window", type=int, default=3, help="steps up to the imagined done the gaps are averaged over")
    ap.add_argument("--gaps-cm", type=float, nargs="*", default=[2.0, 3.0, 4.0, 6.0])
    ap.add_argument("--seed", type=int, default=2_000_000)
    args = ap.parse_args()
    torch.set_num_threads(1)

    from stages.common.proprio import tcp_position_m
    from stages.evaluate.stats import wilson
    from stages.rl.imagined import imagine_and_replay
    from stages.sft.policy import POLICY_FILE

    c = load_check(args.collect, args.tokenize, args.train_wm, args.sft, args.sft / POLICY_FILE, split=args.split,
                   envs=args.envs, steps=args.steps)
    tok = c.tok
    codes_fn = lambda t: tok.codes(torch.from_numpy(np.asarray(t, np.int64).reshape(len(t), *tok.grid)))  # noqa: E731
    data = load_data(args.export)
    if tuple(data["grid"]) != tuple(tok.grid):
        raise SystemExit(f"the export's grid {tuple(data['grid'])} is not the tokenizer's {tuple(tok.grid)}")
    torch.manual_seed(0)
    locator = ArmLocator(tok.bits, tok.grid)
    fit = fit_locator(locator, *frames_and_tcp(data["train"], codes_fn), args.locator_steps, seed=0)
    locator.eval()
    for split in ("heldout", "ood"):
        if not data[split]:
            continue
        codes, tcp = frames_and_tcp(data[split], codes_fn)
        err = 100 * np.linalg.norm(locate(locator, codes) - tcp.numpy(), axis=1)
        print(f"arm locator on real {split} frames ({len(err)}): TCP error mean {err.mean():.2f} cm, "
              f"median {np.median(err):.2f}, 95th percentile {np.percentile(err, 95):.2f} ({fit['seconds']:.0f} s fit)")

    record = {}
    try:
        rows = imagine_and_replay(c.policy, c.wm, tok, c.obs_fn, c.sim, c.specs,
                                  [args.seed + i for i in range(len(c.specs))], args.steps, args.theta, record=record)
    finally:
        c.sim.close()
    n, t1 = record["tokens"].shape[:2]
    located = locate(locator, tok.codes(record["tokens"][:, 1:].reshape(-1, *tok.grid))).reshape(n, t1 - 1, 3)
    imagined = tcp_position_m(record["proprio"])  # (N, T, 3)
    print(f"policy sft: {n} {args.split.upper()} environments, {args.steps} policy steps, theta {args.theta}")
    print(f"  per imagined success, mean over the {args.window} steps up to its imagined done (cm): "
          "located-vs-imagined-proprio | located-vs-replayed TCP | imagined-proprio-vs-replayed TCP")
    obs_gap = {}
    for i, r in enumerate(rows):
        if r.done_at < 0:
            continue
        k = r.done_at
        s = slice(max(0, k - args.window), k)  # steps k-window+1 .. k (0-based indices of frames 1..T)
        g_obs = 100 * float(np.linalg.norm(located[i, s] - imagined[i, s], axis=1).mean())
        real = tcp_position_m(np.asarray(record["replay_proprio"][i][:k]))  # the replay may have ended sooner
        m = len(real)
        s = slice(max(0, m - args.window), m)
        g_real = 100 * float(np.linalg.norm(located[i, s] - real[s], axis=1).mean()) if m else float("nan")
        g_prop = 100 * float(np.linalg.norm(imagined[i, s] - real[s], axis=1).mean()) if m else float("nan")
        obs_gap[i] = g_obs
        print(f"    {r.env_id:55s} done_at {k:3d}  replay {'confirms' if r.success else 'does not':9s}  "
              f"{g_obs:5.1f} | {g_real:5.1f} | {g_prop:5.1f}")
    for name, keep in (("confirmed", True), ("not confirmed", False)):
        v = sorted(obs_gap[i] for i in obs_gap if rows[i].success == keep)
        print(f"  observable gap, {name} ({len(v)}): median {np.median(v) if v else float('nan'):.1f} cm, "
              f"values {', '.join(f'{x:.1f}' for x in v)}")
    for g in args.gaps_cm:
        kept = [i for i in obs_gap if obs_gap[i] <= g]
        true = sum(rows[i].success for i in kept)
        p, lo, hi = wilson(true, len(kept)) if kept else (float("nan"),) * 3
        print(f"  veto above {g:.1f} cm: imagined successes kept {len(kept)} of {len(obs_gap)}, confirmed {true} "
              f"of {sum(rows[i].success for i in obs_gap)}, precision {p:.2f} [{lo:.2f}, {hi:.2f}]")


if __name__ == "__main__":
    main()

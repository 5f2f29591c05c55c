"""Evaluation of trained world models: open-loop frame quality, done head, controllability, extreme actions.

Frames are compared as one image per time step: the third view and the wrist view side by side,
(3, S, 2S) in [0, 1], real frames resized to the tokenizer's resolution. Three rows per horizon:
the world model's open-loop prediction, the copy-the-last-frame baseline (the start frame through
the same tokenizer decoder), and the tokenizer ceiling (the real frame's own tokens decoded).
"""
from __future__ import annotations

import numpy as np
import torch

from stages.common import image_metrics
from stages.train_wm.data import Episode
from stages.train_wm.rollout import WorldModel

HORIZONS = (1, 5, 15)


def side_by_side(third: torch.Tensor, wrist: torch.Tensor) -> torch.Tensor:
    """(N, 3, S, S) x 2 -> (N, 3, S, 2S)."""
    return torch.cat([third, wrist], dim=-1)


def real_images(tok, third: np.ndarray, wrist: np.ndarray) -> torch.Tensor:
    """Real uint8 views (N, H, W, 3) at the tokenizer's resolution, side by side (N, 3, S, 2S) in [0, 1]."""
    from stages.tokenize.model import from_obs, to_obs

    return side_by_side(*from_obs(to_obs(torch.as_tensor(third), torch.as_tensor(wrist), tok.image_size)))


def decoded(tok, tokens: torch.Tensor) -> torch.Tensor:
    """Token grids (N, h, w) decoded side by side (N, 3, S, 2S), on the CPU (beside the real frames)."""
    return side_by_side(*tok.decode(tokens)).cpu()


def rollout_starts(episodes: list[Episode], horizon: int, per_episode: int, rng: np.random.Generator) -> list[tuple]:
    """(episode index, start frame) pairs with ``horizon`` true actions after the start."""
    out = []
    for i, ep in enumerate(episodes):
        last = ep.length - horizon
        if last < 0:
            continue
        for s in rng.choice(last + 1, size=min(per_episode, last + 1), replace=False):
            out.append((i, int(s)))
    return out


@torch.no_grad()
def open_loop(wm: WorldModel, episodes: list[Episode], starts: list[tuple], horizon: int,
              actions: torch.Tensor | None = None, text: torch.Tensor | None = None) -> torch.Tensor:
    """Predicted tokens (K, horizon, N) from real start frames under ``actions`` (K, horizon, 7) or text (K, 384)."""
    h, w = wm.spec.grid
    k = len(starts)
    tokens0 = torch.stack([torch.from_numpy(episodes[i].tokens[s]) for i, s in starts]).view(k, h, w)
    roll = wm.rollout(k)
    roll.reset(tokens0, text)
    preds = []
    for t in range(horizon):
        preds.append(roll.step(actions[:, t] if actions is not None else None).tokens.reshape(k, -1))
    return torch.stack(preds, 1)


def true_actions(episodes: list[Episode], starts: list[tuple], horizon: int) -> torch.Tensor:
    """(K, horizon, 7) recorded actions after each start."""
    return torch.stack([torch.from_numpy(episodes[i].actions[s : s + horizon]) for i, s in starts])


def frame_metrics(tok, pred_tokens: torch.Tensor, real: torch.Tensor, device: str) -> dict[str, float]:
    """Mean PSNR / SSIM / LPIPS of decoded ``pred_tokens`` (K, h, w) against real images (K, 3, S, 2S)."""
    return image_metrics.summary(decoded(tok, pred_tokens).clamp(0, 1), real, device)


def auroc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve (rank statistic, ties averaged); NaN when a class is absent."""
    pos, neg = label > 0.5, label <= 0.5
    if pos.sum() == 0 or neg.sum() == 0:
        return float("nan")
    order = np.argsort(score, kind="mergesort")
    ranks = np.empty(len(score))
    sorted_scores = score[order]
    i = 0
    while i < len(score):  # average ranks over ties
        j = i
        while j + 1 < len(score) and sorted_scores[j + 1] == sorted_scores[i]:
            j += 1
        ranks[order[i : j + 1]] = (i + j) / 2 + 1
        i = j + 1
    return float((ranks[pos].sum() - pos.sum() * (pos.sum() + 1) / 2) / (pos.sum() * neg.sum()))


def done_metrics(prob: np.ndarray, label: np.ndarray, theta: float) -> dict[str, float]:
    """AUROC, precision/recall at ``theta``, Brier score and 10-bin expected calibration error."""
    pred = prob >= theta
    pos = label > 0.5
    tp = float((pred & pos).sum())
    bins = np.minimum((prob * 10).astype(int), 9)
    ece = sum(abs(prob[bins == b].mean() - label[bins == b].mean()) * (bins == b).mean()
              for b in range(10) if (bins == b).any())
    return {"auroc": auroc(prob, label),
            "precision": tp / pred.sum() if pred.sum() else float("nan"),
            "recall": tp / pos.sum() if pos.sum() else float("nan"),
            "brier": float(((prob - label) ** 2).mean()), "ece": float(ece),
            "positive_rate": float(pos.mean()), "frames": int(len(label))}


@torch.no_grad()
def done_probabilities(wm: WorldModel, episodes: list[Episode], text_emb: dict) -> list[np.ndarray]:
    """Done-head probabilities of teacher-forced real sequences, (T,) per episode for frames 1..T.

    All episodes run as one batch, padded to the longest with their last frame (and zero actions);
    the causal model makes the padding invisible to the real frames, whose outputs alone are kept.
    """
    h, w = wm.spec.grid
    t_max = max(ep.length for ep in episodes)
    tokens = torch.zeros(len(episodes), t_max + 1, h * w, dtype=torch.long)
    actions = torch.zeros(len(episodes), t_max, 7)
    for b, ep in enumerate(episodes):
        tokens[b, : ep.length + 1] = torch.from_numpy(ep.tokens)
        tokens[b, ep.length + 1 :] = torch.from_numpy(ep.tokens[-1])
        actions[b, : ep.length] = torch.from_numpy(ep.actions)
    if wm.spec.kind == "action":
        control = actions
    else:
        control = torch.stack([torch.from_numpy(text_emb[ep.instruction]) for ep in episodes])
    prob = wm.done_for_sequences(tokens.view(len(episodes), t_max + 1, h, w), control).cpu().numpy()
    return [prob[b, : ep.length] for b, ep in enumerate(episodes)]


@torch.no_grad()
def done_head_eval(wm: WorldModel, episodes: list[Episode], theta: float, text_emb: dict) -> dict[str, float]:
    """Done-head metrics of teacher-forced real sequences against the simulator's success (frames 1..T)."""
    if not episodes:
        return {}
    probs = np.concatenate(done_probabilities(wm, episodes, text_emb))
    labels = np.concatenate([ep.done[1:] for ep in episodes])
    return done_metrics(probs, labels, theta)


@torch.no_grad()
def false_alarm_rate(wm: WorldModel, episodes: list[Episode], theta: float, text_emb: dict) -> dict[str, float]:
    """On episodes that never succeed (near-misses): the fraction whose done probability reaches
    ``theta`` at some frame (each would end an imagined episode as a success), and the mean peak."""
    if not episodes:
        return {}
    peaks = np.array([p.max() for p in done_probabilities(wm, episodes, text_emb)])
    return {"false_alarm_rate": float((peaks >= theta).mean()), "mean_peak_prob": float(peaks.mean()),
            "episodes": len(episodes)}


@torch.no_grad()
def horizon_eval(wm: WorldModel, tok, episodes: list[Episode], images: dict, starts: list[tuple],
                 text_emb: dict, device: str, controllability: bool) -> tuple[dict, dict]:
    """Metrics at each horizon (WM, copy-last baseline, tokenizer ceiling; shuffled actions when asked).

    ``images[episode_id]`` = real side-by-side frames (T+1, 3, S, 2S). Returns (metrics, strips for the figure).
    """
    hmax = max(HORIZONS)
    k = len(starts)
    h, w = wm.spec.grid
    if wm.spec.kind == "action":
        acts = true_actions(episodes, starts, hmax)
        pred = open_loop(wm, episodes, starts, hmax, actions=acts).cpu()  # (K, hmax, N), beside the CPU real tokens
    else:
        text = torch.stack([torch.from_numpy(text_emb[episodes[i].instruction]) for i, _ in starts])
        pred = open_loop(wm, episodes, starts, hmax, text=text).cpu()
    shuffled = None
    if controllability and k > 1:
        # each start gets another start's action sequence (a derangement: never its own)
        perm = (torch.arange(k) + 1 + torch.randint(0, k - 1, (1,), generator=torch.Generator().manual_seed(0))) % k
        shuffled = open_loop(wm, episodes, starts, hmax, actions=acts[perm]).cpu()
    start_tok = torch.stack([torch.from_numpy(episodes[i].tokens[s]) for i, s in starts]).view(k, h, w)
    metrics = {}
    for hz in HORIZONS:
        real = torch.stack([images[episodes[i].episode_id][s + hz] for i, s in starts])
        real_tok = torch.stack([torch.from_numpy(episodes[i].tokens[s + hz]) for i, s in starts]).view(k, h, w)
        rows = {"wm": pred[:, hz - 1].view(k, h, w), "copy_last": start_tok, "tokenizer": real_tok}
        if shuffled is not None:
            rows["shuffled_actions"] = shuffled[:, hz - 1].view(k, h, w)
        for name, toks in rows.items():
            for m, v in frame_metrics(tok, toks, real, device).items():
                metrics[f"h{hz}/{name}/{m}"] = v
        metrics[f"h{hz}/wm/token_acc"] = float((pred[:, hz - 1] == real_tok.view(k, -1)).float().mean())
        # paired per-start PSNR difference to copy-last, with a normal 95% half-width (same starts, same frames)
        diff = (image_metrics.psnr(decoded(tok, rows["wm"]).clamp(0, 1), real)
                - image_metrics.psnr(decoded(tok, start_tok).clamp(0, 1), real)).double()
        diff = diff[torch.isfinite(diff)]
        metrics[f"h{hz}/wm_minus_copy/psnr"] = float(diff.mean()) if len(diff) else float("nan")
        metrics[f"h{hz}/wm_minus_copy/psnr_ci95"] = float(1.96 * diff.std() / len(diff) ** 0.5) if len(diff) > 1 else float("nan")
        metrics[f"h{hz}/copy_last/token_acc"] = float((start_tok == real_tok).float().mean())
        if shuffled is not None:
            metrics[f"h{hz}/shuffled_actions/token_acc"] = float((shuffled[:, hz - 1] == real_tok.view(k, -1)).float().mean())
            metrics[f"h{hz}/true_vs_shuffled_pixel_l1"] = float(
                (decoded(tok, rows["wm"]) - decoded(tok, rows["shuffled_actions"])).abs().mean())
    metrics["starts"] = k
    strip = {"start": starts[0], "pred": pred[0].view(hmax, h, w)}
    return metrics, strip


@torch.no_grad()
def extreme_action_eval(wm: WorldModel, tok, episodes: list[Episode], starts: list[tuple], steps: int,
                        scale: float, seed: int) -> dict[str, float]:
    """Roll out with actions ``scale`` x beyond the data range (random signs): finite and decodable?"""
    k = len(starts)
    h, w = wm.spec.grid
    gen = torch.Generator().manual_seed(seed)
    bound = torch.maximum(wm.net.action_low.abs(), wm.net.action_high.abs()).cpu()
    tokens0 = torch.stack([torch.from_numpy(episodes[i].tokens[s]) for i, s in starts]).view(k, h, w)
    roll = wm.rollout(k)
    roll.reset(tokens0)
    finite, last = True, None
    for _ in range(steps):
        a = (torch.randint(0, 2, (k, 7), generator=gen).float() * 2 - 1) * bound * scale
        out = roll.step(a)
        finite &= bool(torch.isfinite(out.done_prob).all() and torch.isfinite(out.hidden).all())
        last = out.tokens
    img = decoded(tok, last)
    return {"finite": float(finite and bool(torch.isfinite(img).all())),
            "clip_fraction": roll.clip_count / (k * steps * 7),
            "decoded_min": float(img.min()), "decoded_max": float(img.max()), "steps": steps, "scale": scale}

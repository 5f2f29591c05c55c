"""Which (task, scene) environments a run uses: the training ones, and a spread of n of them."""
from __future__ import annotations


def training_environments(envs: list, train_ids, tasks: list[str]) -> list:
    """The IND environments (``stages.goals.environments.Environment``) of ``tasks`` with at least one
    episode among ``train_ids``: where the world model was trained, where PPO and the play run."""
    train = set(train_ids)
    out = [e for e in envs if e.split == "ind" and e.task in tasks and any(i in train for i in e.episodes)]
    if not out:
        raise ValueError(f"no in-domain training environments for tasks {tasks}")
    return out


def pick_environments(envs: list, n: int) -> list:
    """Up to ``n`` environments spread round-robin over their tasks (sorted), in a fixed order."""
    by_task: dict[str, list] = {}
    for e in envs:
        by_task.setdefault(e.task, []).append(e)
    tasks = sorted(by_task)
    if not tasks:
        return []
    return [by_task[tasks[i % len(tasks)]][(i // len(tasks)) % len(by_task[tasks[i % len(tasks)]])]
            for i in range(n)]

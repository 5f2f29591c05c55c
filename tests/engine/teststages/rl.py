"""Test stage 'rl'."""
from tests.engine.teststages.common import Config, run_stage


def used_needs(cfg):
    """Like the real rl stage with the simulator's reward: a config may read fewer inputs than declared."""
    return cfg.reads if cfg.reads is not None else ["goals", "train_wm"]


def run(ctx):
    run_stage(ctx)

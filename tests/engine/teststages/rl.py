"""Test stage 'rl'."""
from tests.engine.teststages.common import Config, run_stage


def unread_needs(cfg):
    """Like the real rl stage with the simulator's reward: a config may read fewer inputs than declared."""
    return cfg.skips


def run(ctx):
    run_stage(ctx)

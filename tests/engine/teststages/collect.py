"""Test stage 'collect'."""
from tests.engine.teststages.common import Config, run_stage


def run(ctx):
    run_stage(ctx)

"""The one exception type the CLI turns into a clean message (no traceback)."""


class PipelineError(Exception):
    """A problem the user can fix: bad pipeline.yaml, unknown stage, bad --set, missing input..."""

"""The base of the pipeline's errors (MCAP → datasets → trained, versioned networks)."""

from __future__ import annotations

from models.errors import VslabError


class PipelineError(VslabError):
    """A stage could not do its work with what it was given (a session, a dataset, a model, a grid)."""

"""The training grid file (``configs/train/*.yaml``) as a pydantic model: what ``vslab schema grid`` turns
into a JSON Schema so that editors complete and check those files.

:func:`pipeline.grid.check_grid` stays the loader's check (its messages name the file or ``--set``); this
model says the same rules as types, and the tests hold the two to each other. It imports nothing heavy (no
torch), so ``vslab schema`` stays quick: the presets, splits and training fields are repeated here and the
tests check them against ``models.hybrid``, ``pipeline.datasets`` and ``pipeline.train``.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

# what models.hybrid.preset, pipeline.datasets.SPLIT_COLUMNS, pipeline.model_store.TAG and
# pipeline.grid.DATASET accept (tests/test_json_schemas.py checks each against its source)
PRESETS = ("paper", "residual", "small-residual", "ensemble-small-residual")
SPLITS = ("split_random", "split_group")
TAG_PATTERN = r"^[a-z][a-z0-9_-]*$"
DATASET_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*(@[A-Za-z0-9_][A-Za-z0-9_.-]*)?$"


def _no_default(schema: dict) -> None:
    """Leave a key's default out of its schema: a key that may be left out, but not set to null."""
    schema.pop("default", None)


def _optional(description: str) -> Any:
    """A key that may be left out (not set to null), with no default of its own to show."""
    return Field(None, description=description, json_schema_extra=_no_default)


class _Strict(BaseModel):
    """Unknown keys refused, no type coercion (``"5"`` is no integer)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


class GridModel(_Strict):
    """One network of the grid: a preset of ``models.hybrid`` for a direction, optionally with its fields
    overridden, optionally tagged (the figures and Experiment 2 find their networks by tag)."""

    direction: Literal["forward", "inverse"] = Field(
        description="Forward (joints, pressures, currents → tip) or inverse (tip → compensated joints)."
    )
    preset: Literal[PRESETS] = Field(description="The network's preset in models.hybrid.")
    tag: Annotated[str, Field(pattern=TAG_PATTERN)] = _optional(
        "A name the trained network gets in <lab>/models/ (lower-case letters, digits, - and _); only in a "
        "grid of one dataset, one split and one seed."
    )
    hidden: Annotated[list[Annotated[int, Field(ge=1)]], Field(min_length=1)] = _optional(
        "Hidden layer widths (default: the preset's)."
    )
    residual: bool = _optional("Predict only the correction over the rigid model (default: the preset's).")
    ensemble: Annotated[int, Field(ge=1)] = _optional("Members averaged (default: the preset's).")
    name: str = _optional("The network's name (default: the preset's).")


class TrainFields(_Strict):
    """Training settings of every job (``pipeline.train.TrainConfig``); ``--set key=value`` overrides one."""

    lr: float = Field(1e-3, gt=0, description="Adam's learning rate (1/step of the standardised loss).")
    batch_size: int = Field(256, ge=1, description="Samples per optimiser step.")
    max_epochs: int = Field(300, ge=1, description="Epochs at most.")
    patience: int = Field(20, ge=0, description="Epochs without a better validation loss before stopping.")
    weight_decay: float = Field(0.0, ge=0, description="Adam's L2 weight decay.")


class GridFile(_Strict):
    """A training grid: every model × dataset × split × seed is one training job; a job whose version exists
    in the lab already is skipped."""

    models: Annotated[list[GridModel], Field(min_length=1)] = _optional(
        "The networks trained (left out: no jobs)."
    )
    datasets: Annotated[list[Annotated[str, Field(pattern=DATASET_PATTERN)]], Field(min_length=1)] = (
        _optional("Datasets of the lab: a name (its newest version) or name@version (left out: no jobs).")
    )
    splits: Annotated[list[Literal[SPLITS]], Field(min_length=1)] = Field(
        ["split_random"], description="How each dataset is dealt into train, validation and test parts."
    )
    seeds: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] = Field(
        [0], description="Random seeds (one job each)."
    )
    train: TrainFields | None = Field(
        None, description="Training settings of every job (none: the defaults)."
    )

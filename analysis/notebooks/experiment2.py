# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Experiment 2 step by step (seed 000, Figs. 6–7)
#
# The curve at 25 g / 1.5 bar and 75 g / 0.5 bar, commanded by the model-based IK, by our grey-box static
# compensation and by the hybrid inverse network. This notebook reads a lab directory that `make demo` (or
# `vslab demo --quick`) has filled, and calls the same functions as `vslab figures`.
# Open it with jupytext (`jupytext --to notebook experiment2.py`) or run it as a script:
# `VSLAB_LAB=lab python analysis/notebooks/experiment2.py`.

# %%
import os

from analysis import vsl_figures, vsl_paths
from pipeline.lab import Lab

lab = Lab.open(os.environ.get("VSLAB_LAB", "lab"))
out = lab.figures / "notebooks"

# %% [markdown]
# The Experiment 2 dataset: trajectory samples in the robot's base frame (the tracker registered with the
# campaign's static points), with the plan each session ran and the commanded joint angles `qc`.

# %%
data, card = lab.datasets.load("experiment2")
print(card["version"], len(data), "rows;", data["plan"].nunique(), "plans")
print(data.groupby("plan").size())

# %% [markdown]
# Each measured point's distance to the desired path, per session (the paper's position error):

# %%
errors = vsl_paths.path_errors(data)
print(errors.round(2).to_string())

# %% [markdown]
# Fig. 7a (paths, commanded path dashed) and Fig. 7b (error boxplots: mean, range, 25–75 % box):

# %%
fig7 = vsl_figures.fig7(data, out, {"dataset experiment2": card["version"]})
print([str(p) for p in fig7.paths])

# %% [markdown]
# The paper's claim: the hybrid-compensated VSL arm is more accurate than the model-based VSL arm and than
# the rigid-link arm with model-based IK.

# %%
means = errors.groupby(["robot", "mode"])["mean_mm"].mean()
print(means.round(2).to_string())

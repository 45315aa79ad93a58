# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # POPUP link tests step by step (seed 001, Fig. 7 and Table 1)
#
# The static test (incremental loading then unloading at 10–50 kPa) and the impact test (free oscillation
# after a hammer tap at 10–90 kPa), recorded on the twin by `make demo`, analysed by the paper's procedure
# with the same functions as `vslab figures`. Run: `VSLAB_LAB=lab python analysis/notebooks/popup_table1.py`.

# %%
import os

from analysis import popup_tests
from pipeline import link_tests
from pipeline.lab import Lab

lab = Lab.open(os.environ.get("VSLAB_LAB", "lab"))
static = sorted(lab.sessions.root.glob("sim-popup_static-*"))
impact = sorted(lab.sessions.root.glob("sim-popup_impact-*"))
print(len(static), "static sessions,", len(impact), "impact sessions")

# %% [markdown]
# Static characteristic: torque about link 2's virtual hinge against its angular deflection, mean of the
# runs, per pressure and branch; then k by linear regression below the wrinkling moment M_w(p), on the
# loading branch as the paper did (its first static tests only loaded the link).

# %%
curves = link_tests.link_static_curves(static)
stiffness = link_tests.static_stiffness(curves)
print(stiffness.round(3).to_string())
popup_tests.figure7(curves, lab.figures / "notebooks")

# %% [markdown]
# Impact test: damped frequency and damping ratio from a damped sinusoid fitted to the accelerometer's free
# oscillation (started from its PSD peak and logarithmic decrement).

# %%
impact_parameters = link_tests.impact_parameters(impact)
print(impact_parameters.round(4).to_string())

# %% [markdown]
# Table 1: one moment of inertia from all pressures, then k̂ and ĉ, beside the paper's values.

# %%
table = popup_tests.table1(stiffness, impact_parameters)
print(popup_tests.table1_markdown(table))

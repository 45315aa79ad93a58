"""Units by name: the code's convention (DESIGN.md) is a quantity's unit at the end of its name
(``settle_s``, ``pressure_bar``, ``stiffness_nm_per_rad``). One table, read wherever a unit is shown beside a
name (the configuration files' schemas, the reference pages)."""

from __future__ import annotations

# name suffix → unit, longest (most specific) first: ``speed_m_s`` is m/s, not s
UNIT_SUFFIXES = (
    ("_m_s2_per_sqrt_hz", "m/s²/√Hz"), ("_nms_per_rad", "N·m·s/rad"), ("_nm_per_rad", "N·m/rad"),
    ("_nm_per_a", "N·m/A"), ("_per_bar", "1/bar"), ("_rad_s2", "rad/s²"), ("_rad_s", "rad/s"),
    ("_m_s2", "m/s²"), ("_m_s", "m/s"), ("_kgm2", "kg·m²"), ("_counts", "counts"), ("_nms", "N·m·s"),
    ("_nm", "N·m"), ("_kpa", "kPa"), ("_pa", "Pa"), ("_bar", "bar"), ("_kg", "kg"), ("_mm", "mm"),
    ("_hz", "Hz"), ("_rad", "rad"), ("_deg", "°"), ("_ms", "ms"), ("_m", "m"), ("_s", "s"), ("_a", "A"),
    ("_v", "V"), ("_g", "g"),
)  # fmt: skip


def unit_of_name(name: str) -> str | None:
    """The unit the end of ``name`` gives (case ignored); None for a count, a name or a fraction."""
    lowered = name.lower()
    return next((unit for suffix, unit in UNIT_SUFFIXES if lowered.endswith(suffix)), None)

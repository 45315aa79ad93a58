"""Robot descriptions: the YAML files of ``configs/robots/`` loaded and validated.

A description holds everything the rest of vslab needs to know about one physical arm: its kinematic chain
(with the pseudo-rigid-body virtual joints of its soft links), masses, joint limits, the stiffness and damping
tables of the links versus pressure, hysteresis, servo/stepper/pneumatic behaviour, sensor noise, device
clocks, the tracker placement and the device ports. Values are SI; the unit is in every field name.
A bad file raises :class:`RobotDescriptionError` with one message naming the file, the field and the reason.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from numpy.typing import ArrayLike
from pydantic import Field, ValidationError, field_validator, model_validator

from models.description_part import NonNegFloat, Part, PositiveFloat
from models.effects import EffectsSpec
from models.errors import ModelError
from models.kinematics import ArmLengths, DHChain, DHRow
from models.yaml_files import read_yaml

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs" / "robots"
CAN_DIR = CONFIG_DIR.parent / "can"  # the CAN devices' EDS and DBC files
TIP_FRAME = "tip"


class RobotDescriptionError(ModelError, ValueError):
    """A robot description file is missing, unreadable or invalid."""


# ---------------------------------------------------------------------------------------------- kinematics
class AnthropomorphicKinematics(Part):
    """The 3-DoF arm of seed 000, eq. (1): J1 about z, J2/J3 in the vertical plane."""

    type: Literal["anthropomorphic"]
    l1_m: PositiveFloat
    l2_m: PositiveFloat
    l3_m: PositiveFloat
    # each joint's true angle minus its encoder's reading: the encoders' zero errors, a lab arm's own
    # (`vslab twin fit` fits them; the papers' arm has none)
    joint_offsets_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def arm(self) -> ArmLengths:
        """The rigid arm of eq. (1) (``models.kinematics``): lengths and joint offsets."""
        return ArmLengths(self.l1_m, self.l2_m, self.l3_m, self.joint_offsets_rad)


class DHRowSpec(Part):
    """One standard D-H row, T = Rz(θ) Tz(d) Tx(a) Rx(α), with θ = joint variable + offset."""

    a_m: float
    alpha_rad: float
    d_m: float
    joint: str
    offset_rad: float = 0.0


class DHKinematics(Part):
    """A general D-H chain; joints named q* are actuated, the others are virtual (link bending)."""

    type: Literal["dh"]
    rows: list[DHRowSpec] = Field(min_length=1)

    @field_validator("rows")
    @classmethod
    def _unique_joints(cls, rows: list[DHRowSpec]) -> list[DHRowSpec]:
        names = [r.joint for r in rows]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"joint names must be unique, repeated: {dupes}")
        return rows


# ----------------------------------------------------------------------------------------------- links
class PressureTable(Part):
    """A link property tabulated against gauge pressure; linear interpolation in between."""

    pressure_pa: list[NonNegFloat] = Field(min_length=2)
    stiffness_nm_per_rad: list[PositiveFloat]
    damping_nms_per_rad: list[NonNegFloat]

    @model_validator(mode="after")
    def _consistent(self) -> PressureTable:
        n = len(self.pressure_pa)
        if len(self.stiffness_nm_per_rad) != n or len(self.damping_nms_per_rad) != n:
            raise ValueError(
                f"pressure_pa has {n} entries but stiffness_nm_per_rad has {len(self.stiffness_nm_per_rad)}"
                f" and damping_nms_per_rad has {len(self.damping_nms_per_rad)}"
            )
        if any(b <= a for a, b in zip(self.pressure_pa, self.pressure_pa[1:], strict=False)):
            raise ValueError("pressure_pa must be strictly increasing")
        return self

    def scaled(self, factor: float) -> PressureTable:
        """The same table with stiffness and damping multiplied by ``factor``."""
        return PressureTable(
            pressure_pa=self.pressure_pa,
            stiffness_nm_per_rad=[k * factor for k in self.stiffness_nm_per_rad],
            damping_nms_per_rad=[c * factor for c in self.damping_nms_per_rad],
        )


class ScaledTable(Part):
    """A table taken from another link and scaled (e.g. by the ratio of second moments of area)."""

    from_link: str
    factor: PositiveFloat


class Hysteresis(Part):
    """Bouc–Wen offset on the link angle: loop width ≈ 2·delta_h_rad once the driving moment's swing ≫
    tau_y_nm. On an inflatable link (``radius_m``) it is driven by the moment beyond M_w(p) only."""

    delta_h_rad: NonNegFloat
    tau_y_nm: PositiveFloat


class LinkSpec(Part):
    """A soft (or rigid-but-compliant) link modelled as a pseudo-rigid body with virtual joints."""

    name: str
    virtual_joints: list[str] = Field(min_length=1)
    after_joint: str | None = None  # anthropomorphic arm: the actuated joint this link follows (q2 or q3)
    radius_m: PositiveFloat | None = None
    hinge_fraction: Annotated[float, Field(ge=0, lt=1)] = 0.15
    table: PressureTable | ScaledTable
    hysteresis: Hysteresis
    pressure_channel: int | None = Field(default=None, ge=0)


class PointMass(Part):
    """A point mass at ``position_m`` in the output frame of the row driven by ``frame`` (or 'tip')."""

    name: str
    mass_kg: NonNegFloat
    frame: str
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia_kgm2: NonNegFloat = 0.0  # about its own centre, for any axis through it (a rod's mL²/12)


class JointSpec(Part):
    name: str
    lower_rad: float
    upper_rad: float
    drive: Literal["servo", "stepper", "motor"]
    _limits = (("lower_rad", "<", "upper_rad"),)


# -------------------------------------------------------------------------------------------- actuators
class ServoSpec(Part):
    """Position-controlled joint drive (Dynamixel-like): profile, finite P-gain, backlash, current model.
    Also used for POPUP's geared brushless motors ('motor' drive)."""

    model: str = "XM430-W350-T"
    p_gain: PositiveFloat
    stiffness_per_p_gain_nm_per_rad: PositiveFloat
    loop_time_constant_s: PositiveFloat
    backlash_rad: NonNegFloat
    torque_constant_nm_per_a: PositiveFloat
    max_torque_nm: PositiveFloat  # stall/peak torque: the drive cannot push harder, whatever the loop asks
    max_speed_rad_s: PositiveFloat  # top speed: what a profile velocity of 0 ("unlimited") really means
    idle_current_a: NonNegFloat
    friction_current_a: NonNegFloat
    rotor_inertia_kgm2: NonNegFloat
    profile_velocity_rad_s: NonNegFloat
    profile_acceleration_rad_s2: NonNegFloat
    zero_count: int = 2048

    @property
    def stiffness_nm_per_rad(self) -> float:
        return self.p_gain * self.stiffness_per_p_gain_nm_per_rad


class StepperSpec(Part):
    steps_per_rev: int = Field(gt=0)
    microsteps: int = Field(gt=0)
    gear_ratio: PositiveFloat
    max_speed_rad_s: PositiveFloat
    acceleration_rad_s2: PositiveFloat
    report_rate_hz: PositiveFloat = 100.0

    @property
    def rad_per_microstep(self) -> float:
        return 2 * math.pi / (self.steps_per_rev * self.microsteps * self.gear_ratio)


class PneumaticsSpec(Part):
    """Regulators (first-order lag + dead time), valves that hold with a slow leak, safety limits."""

    channels: int = Field(gt=0)
    regulator_time_constant_s: PositiveFloat
    regulator_dead_time_s: NonNegFloat
    regulator_max_pa: PositiveFloat
    leak_time_constant_s: PositiveFloat
    min_operating_pa: NonNegFloat
    max_operating_pa: PositiveFloat
    _limits = (("min_operating_pa", "<", "max_operating_pa"), ("max_operating_pa", "<=", "regulator_max_pa"))


# ---------------------------------------------------------------------------------------------- sensors
class PressureSensorSpec(Part):
    """The pressure transducers' calibration: gauge 0…full_scale_pa ↔ v_min…v_max V, read by a 16-bit ADC
    (``adc_lsb_v`` per count). One line, used alike by the recorder (counts → Pa), the twin (Pa → counts,
    plus noise) and the pipeline."""

    full_scale_pa: PositiveFloat
    v_min: float
    v_max: float
    adc_lsb_v: PositiveFloat
    adc_noise_v: NonNegFloat
    sample_rate_hz: PositiveFloat
    _limits = (("v_min", "<", "v_max"),)

    def counts_to_pa(self, counts: np.ndarray) -> np.ndarray:
        """Gauge pressure (Pa) of ADC counts."""
        volts = np.asarray(counts, dtype=float) * self.adc_lsb_v
        return (volts - self.v_min) / (self.v_max - self.v_min) * self.full_scale_pa

    def pa_to_volts(self, pressure_pa: np.ndarray) -> np.ndarray:
        """The transducer's output (V) for a gauge pressure, its range clipped (no noise, no ADC)."""
        p = np.clip(np.asarray(pressure_pa, dtype=float), 0.0, self.full_scale_pa)
        return self.v_min + p / self.full_scale_pa * (self.v_max - self.v_min)


class ServoSensorSpec(Part):
    current_noise_counts: NonNegFloat
    velocity_noise_counts: NonNegFloat


class TrackerSpec(Part):
    """Aurora-like tracker: placement of its field generator relative to the robot base (unknown to the
    pipeline), noise, field volume (box in tracker coordinates) and frame rate."""

    base_to_tracker_rpy_rad: tuple[float, float, float]
    base_to_tracker_translation_m: tuple[float, float, float]
    noise_m: NonNegFloat
    rms_error_mm: NonNegFloat
    field_min_m: tuple[float, float, float]
    field_max_m: tuple[float, float, float]
    frame_rate_hz: PositiveFloat
    _limits = (("field_min_m", "<", "field_max_m"),)


class AccelerometerSpec(Part):
    """3-axis MEMS accelerometer at the end of the chain ('tip'): reads the specific force R^T (a − g) in
    its own frame (the tip frame), with white noise over its bandwidth, quantised and clipped."""

    frame: Literal["tip"] = "tip"
    device: str = "accelerometer"  # the device that reads it (POPUP: link 2's board, at the link's end)
    full_scale_m_s2: PositiveFloat
    lsb_m_s2: PositiveFloat
    noise_density_m_s2_per_sqrt_hz: NonNegFloat
    bandwidth_hz: PositiveFloat
    sample_rate_hz: PositiveFloat
    _limits = (("lsb_m_s2", "<", "full_scale_m_s2"),)

    @property
    def noise_rms_m_s2(self) -> float:
        """White noise per axis over the sensor's bandwidth."""
        return self.noise_density_m_s2_per_sqrt_hz * math.sqrt(self.bandwidth_hz)

    @model_validator(mode="after")
    def _nyquist(self) -> AccelerometerSpec:
        if self.bandwidth_hz > self.sample_rate_hz / 2:
            raise ValueError("bandwidth_hz exceeds the Nyquist frequency sample_rate_hz / 2")
        return self


class FlexSensorSpec(Part):
    """Four resistive flex sensors around an inflatable link (at 0°, 90°, 180°, 270° about its axis), read by
    the link's board: sensor i reads the link's bend κ_i = δ_a cos φ_i + δ_b sin φ_i (its two virtual
    joints) as ADC counts about ``counts_straight``, with white noise, clipped to the ADC's range."""

    counts_straight: Annotated[int, Field(ge=0, le=4095)] = 2048
    counts_per_rad: float = Field(gt=0)
    noise_counts: NonNegFloat = 0.0
    adc_max_counts: Annotated[int, Field(gt=0)] = 4095


class SensorsSpec(Part):
    servo: ServoSensorSpec | None = None
    pressure: PressureSensorSpec
    tracker: TrackerSpec
    accelerometer: AccelerometerSpec | None = None
    flex: FlexSensorSpec | None = None


class ClockDescription(Part):
    """What the description says of a device's counter (its YAML ``clock:``): the twin simulates it
    (``twin.clocks.SimulatedClockSpec``), the pipeline fits it (``pipeline.clock.ClockFitter``)."""

    tick_s: PositiveFloat
    wrap: int | None = Field(default=None, gt=1)
    drift_ppm_sigma: NonNegFloat
    offset_max_s: NonNegFloat


class HostLinkDescription(Part):
    """What the description says of the delay from a device to the host (its YAML ``host_link:``)."""

    latency_s: NonNegFloat
    jitter_s: NonNegFloat
    kind: Literal["exponential", "uniform"] = "uniform"
    # the USB-serial adapter's latency timer as the lab set it (an FTDI's: 16 ms as the driver sets it, 1 ms
    # once a udev rule sets it); 0: no latency timer (a USB CDC device such as an Uno's 16U2 or an slcan
    # adapter forwards each transfer at once)
    latency_timer_s: NonNegFloat = 0.016


class DeviceSpec(Part):
    """One device: which driver speaks to it, where it is plugged in, how often it is read (``rate_hz``:
    the poll rate of a polled device, the stream rate of a streaming one, the frame rate of the tracker),
    its clock and its USB link to the host."""

    driver: str = Field(min_length=1)
    port: str = "auto"
    rate_hz: PositiveFloat | None = None
    baud: int = Field(default=1_000_000, gt=0)
    return_delay_s: NonNegFloat = 0.0  # a Dynamixel's Return Delay Time as the lab set it (factory: 500 µs)
    ids: dict[str, int] = Field(default_factory=dict)
    bus: str | None = None  # a device on another device's bus (a CAN board): that device's port reaches it
    link: str | None = None  # a link board: the link it sits on
    clock: ClockDescription
    host_link: HostLinkDescription


class SafetySpec(Part):
    """Limits beyond the joints' and the pneumatics' own: the tip's allowed box (base frame) and how close to
    the wrinkling moment M_w(p) an inflatable link (one with ``radius_m``) may be loaded."""

    workspace_min_m: tuple[float, float, float]
    workspace_max_m: tuple[float, float, float]
    wrinkling_fraction: Annotated[float, Field(gt=0, le=1)] = 1.0  # of M_w: the limit of ordinary plans
    collapse_fraction: Annotated[float, Field(gt=0, le=1)] = 0.9  # of M_c: plans that allow wrinkling
    pressure_tolerance_pa: NonNegFloat = 5000.0  # measured pressure may overshoot max_operating_pa by this
    _limits = (("workspace_min_m", "<", "workspace_max_m"),)


class FittedValue(Part):
    """One fitted parameter: its value, standard error and the nominal description's value (SI units)."""

    value: float
    stderr: NonNegFloat
    nominal: float


class FittedTrackerField(Part):
    """The tracker's field distortion a fit found in its residuals (``pipeline.tracker_field``): its size per
    axis, the distance it changes over and the noise beside it."""

    rms_mm: NonNegFloat
    length_scale_mm: NonNegFloat
    noise_mm: NonNegFloat


class FittedFactor(Part):
    """A factor on a fitted table and its standard error."""

    factor: PositiveFloat
    stderr: NonNegFloat


class FittedDamping(Part):
    """How the links' damping was fitted to their swings after each move (``pipeline.damping_fit``): over how
    many moves, what the swings left (per axis), how far the tracker lagged the goals' stamps, and what the
    swings' frequency says of each link's fitted stiffness table (a factor on it; a check, not written)."""

    moves: int = Field(ge=0)
    swing_residual_rms_mm: NonNegFloat
    tracker_lag_s: float
    stiffness_from_swings: dict[str, FittedFactor] = Field(default_factory=dict)


class FittedBlock(Part):
    """What `vslab twin fit` fitted into this description (``pipeline.twin_fit``): from which dataset, with
    which code, how well (the tracked tip's residual per axis), the tracker field's distortion it found
    (None: none), the links' damping fit (None: not fitted), each value with its standard error, and what the
    data could not identify, with why (left at the nominal value)."""

    dataset: str
    code_version: str
    points: int = Field(ge=0)
    sessions: int = Field(ge=0)
    residual_rms_mm: NonNegFloat
    registration_correction: dict[str, list[float]]  # the tracker registration's rotation vector and shift
    tracker_field: FittedTrackerField | None = None
    damping: FittedDamping | None = None
    parameters: dict[str, FittedValue]
    not_identifiable: dict[str, str]


class LinkTestsFittedBlock(Part):
    """What `vslab twin fit` fitted into a POPUP description from the lab's link tests
    (``pipeline.popup_fit``): which tests, with which code, each value with its standard error, what the
    tests could not identify, with why, and Table 1 as measured (one record per tapped pressure)."""

    link_tests: str
    code_version: str
    static_holds: int = Field(ge=0)
    taps: int = Field(ge=0)
    parameters: dict[str, FittedValue]
    not_identifiable: dict[str, str]
    table1: list[dict[str, float | None]]  # None: not measured (no static test at that pressure)


# ------------------------------------------------------------------------------------------- the robot
class RobotDescription(Part):
    """A validated robot description; use :func:`load_robot` to read one."""

    name: str
    description: str
    kinematics: AnthropomorphicKinematics | DHKinematics = Field(discriminator="type")
    joints: list[JointSpec] = Field(min_length=1)
    links: list[LinkSpec]
    masses: list[PointMass]
    tool_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    servo: ServoSpec | None = None
    stepper: StepperSpec | None = None
    pneumatics: PneumaticsSpec
    sensors: SensorsSpec
    devices: dict[str, DeviceSpec]
    safety: SafetySpec | None = None
    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81)
    effects: EffectsSpec = EffectsSpec()  # unmodelled effects the twin adds (models.effects); none by default
    fitted: FittedBlock | LinkTestsFittedBlock | None = None  # `vslab twin fit` wrote it: what, how well

    @model_validator(mode="after")
    def _cross_checks(self) -> RobotDescription:
        if isinstance(self.kinematics, AnthropomorphicKinematics):
            for link in self.links:
                if link.after_joint not in ("q2", "q3") or len(link.virtual_joints) != 1:
                    raise ValueError(
                        f"link {link.name!r}: on an anthropomorphic arm a link needs after_joint q2 or q3"
                        " and exactly one virtual joint (in-plane bending)"
                    )
        rows = self.dh_rows()
        row_joints = [r.joint for r in rows]
        actuated = [j for j in row_joints if j.startswith("q")]
        declared = [j.name for j in self.joints]
        if declared != actuated:
            raise ValueError(f"joints {declared} must list the chain's actuated joints in order: {actuated}")
        link_names = [link.name for link in self.links]
        for link in self.links:
            missing = [v for v in link.virtual_joints if v not in row_joints]
            if missing:
                raise ValueError(f"link {link.name!r}: virtual joints {missing} are not in the chain")
            if isinstance(link.table, ScaledTable) and link.table.from_link not in link_names:
                raise ValueError(f"link {link.name!r}: from_link {link.table.from_link!r} is not a link")
            if link.pressure_channel is not None and link.pressure_channel >= self.pneumatics.channels:
                raise ValueError(f"link {link.name!r}: pressure_channel exceeds pneumatics.channels")
        for link in self.links:
            # At rest δ = τ/k − δ_h z with dz/dτ ≤ 1/τ_y: below τ_y = k δ_h a load would move the link against
            # itself (the tip rises when a mass is hung). A loop of full width 2 δ_h needs load swings ≫ τ_y.
            k_max = max(self.link_table(link.name).stiffness_nm_per_rad)
            h = link.hysteresis
            if h.delta_h_rad > 0 and h.tau_y_nm < k_max * h.delta_h_rad * (1 - 1e-6):
                raise ValueError(
                    f"link {link.name!r}: hysteresis tau_y_nm {h.tau_y_nm:g} is below k_max·delta_h_rad = "
                    f"{k_max * h.delta_h_rad:.3g} N·m: the link would deflect against its load"
                )
        frames = {*row_joints, TIP_FRAME}
        for m in self.masses:
            if m.frame not in frames:
                raise ValueError(f"mass {m.name!r}: frame {m.frame!r} is not one of {sorted(frames)}")
        if "accelerometer" in self.devices and self.sensors.accelerometer is None:
            raise ValueError("devices has an accelerometer but sensors has no accelerometer section")
        accel = self.sensors.accelerometer
        if accel is not None and accel.device not in self.devices:
            raise ValueError(f"sensors.accelerometer.device {accel.device!r} is not one of the devices")
        for name, dev in self.devices.items():
            if dev.bus is not None and (dev.bus not in self.devices or self.devices[dev.bus].bus is not None):
                raise ValueError(f"devices.{name}.bus {dev.bus!r} is not a device with a port of its own")
            if dev.link is not None and dev.link not in link_names:
                raise ValueError(f"devices.{name}.link {dev.link!r} is not one of the links {link_names}")
        hoses = self.effects.hoses
        if hoses is not None and (unknown := sorted(set(hoses.joints) - {j.name for j in self.joints})):
            raise ValueError(f"effects.hoses.joints {unknown} are not actuated joints of this robot")
        drives = {j.drive for j in self.joints}
        if drives & {"servo", "motor"} and self.servo is None:
            raise ValueError(
                "joints use a position-controlled drive ('servo'/'motor') but there is no servo section"
            )
        if "stepper" in drives and self.stepper is None:
            raise ValueError("joints use drive 'stepper' but there is no stepper section")
        return self

    # ------------------------------------------------------------------ derived, plain-number views
    def link_end(self, link: str) -> tuple[int, list[int]]:
        """(index of the frame at ``link``'s end in ``chain().frames``, the indices of its two virtual joints
        in δ): where its board's IMU sits and what bends its flex sensors."""
        spec = next(lk for lk in self.links if lk.name == link)
        chain = self.chain()
        frame = [row.joint for row in chain.rows].index(spec.virtual_joints[-1]) + 1
        return frame, [chain.virtual.index(v) for v in spec.virtual_joints]

    def dh_rows(self) -> list[DHRowSpec]:
        """The full chain including virtual joints (for the anthropomorphic arm: generated from L1–L3)."""
        kin = self.kinematics
        if isinstance(kin, DHKinematics):
            return list(kin.rows)
        # rows made of fields validated already (constructed, not validated again: the statics ask for them
        # many times per compensated command, and validating each row cost ~70 % of a command's 18 ms)
        row = DHRowSpec.model_construct
        hinge = {v: link.hinge_fraction for link in self.links for v in link.virtual_joints}
        o1, o2, o3 = kin.joint_offsets_rad
        rows = [row(a_m=0.0, alpha_rad=math.pi / 2, d_m=kin.l1_m, joint="q1", offset_rad=o1)]
        for q, length, offset in (("q2", kin.l2_m, o2), ("q3", kin.l3_m, o3)):
            virtual = [v for link in self.links if link.after_joint == q for v in link.virtual_joints]
            if not virtual:
                rows.append(row(a_m=length, alpha_rad=0.0, d_m=0.0, joint=q, offset_rad=offset))
                continue
            frac = hinge[virtual[0]]
            rows.append(row(a_m=frac * length, alpha_rad=0.0, d_m=0.0, joint=q, offset_rad=offset))
            bend = virtual[0]
            rows.append(row(a_m=(1 - frac) * length, alpha_rad=0.0, d_m=0.0, joint=bend, offset_rad=0.0))
        return rows

    def elongating_rows(self, strain_per_bar: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Which D-H rows lengthen with pressure (``effects.elongation``: a pressurised link's virtual joints'
        rows and the row of the joint it follows): each row's pressure channel (−1: none) and strain per Pa
        (``strain_per_bar`` instead of the description's, e.g. a fit's). Zeros without elongation."""
        rows = [r.joint for r in self.dh_rows()]
        channel, strain = np.full(len(rows), -1), np.zeros(len(rows))
        elongation = self.effects.elongation
        per_bar = strain_per_bar if strain_per_bar is not None else (elongation.strain_per_bar if elongation
                                                                     else 0.0)  # fmt: skip
        if per_bar:
            for link in self.links:
                if link.pressure_channel is None:
                    continue
                for i, name in enumerate(rows):
                    if name in link.virtual_joints or name == link.after_joint:
                        channel[i], strain[i] = link.pressure_channel, per_bar / 1e5
        return channel, strain

    def row_lengths(self, pressure_pa: ArrayLike, strain_per_bar: float | None = None) -> np.ndarray:
        """Every D-H row's length a (..., R) at link pressures (..., channels): a₀ (1 + ε p) on the rows that
        lengthen (:meth:`elongating_rows`), a₀ on the others (the twin's kernel computes the same)."""
        a0 = np.array([r.a_m for r in self.dh_rows()])
        channel, strain = self.elongating_rows(strain_per_bar)
        p = np.asarray(pressure_pa, float)
        on = channel >= 0
        gauge = np.where(on, p[..., np.maximum(channel, 0)], 0.0)
        return a0 * (1.0 + strain * gauge)

    def chain(self) -> DHChain:
        """The kinematic chain (virtual joints included) as a :class:`models.kinematics.DHChain`."""
        return DHChain([DHRow(r.a_m, r.alpha_rad, r.d_m, r.joint, r.offset_rad) for r in self.dh_rows()])

    @property
    def actuated_joints(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def virtual_joints(self) -> list[str]:
        """Virtual joint names in chain order."""
        return [r.joint for r in self.dh_rows() if not r.joint.startswith("q")]

    def link_of(self, virtual_joint: str) -> LinkSpec:
        """The link a virtual joint belongs to."""
        for link in self.links:
            if virtual_joint in link.virtual_joints:
                return link
        raise KeyError(f"robot {self.name!r} has no virtual joint {virtual_joint!r}")

    def link_table(self, link_name: str) -> PressureTable:
        """The resolved pressure table of a link (following ``from_link`` scaling)."""
        link = self._link(link_name)
        if isinstance(link.table, ScaledTable):
            return self.link_table(link.table.from_link).scaled(link.table.factor)
        return link.table

    def joint_limits(self) -> np.ndarray:
        """(n_actuated, 2) lower/upper limits in rad."""
        return np.array([[j.lower_rad, j.upper_rad] for j in self.joints])

    def _link(self, name: str) -> LinkSpec:
        for link in self.links:
            if link.name == name:
                return link
        raise KeyError(f"robot {self.name!r} has no link {name!r}")


# ------------------------------------------------------------------------------------------- loading
def robot_path(name_or_path: str | Path) -> Path:
    """A robot name ('vsl', 'popup', …) resolves to ``configs/robots/<name>.yaml``; a path is kept."""
    p = Path(name_or_path)
    if p.suffix in {".yaml", ".yml"} or p.exists():
        return p
    return CONFIG_DIR / f"{name_or_path}.yaml"


def load_robot(name_or_path: str | Path) -> RobotDescription:
    """Read and validate a robot description; every problem ends in one :class:`RobotDescriptionError`.
    A description may start from another (``extends: NAME`` or a path beside it) and say only what differs:
    its mappings are merged into the base's, key by key; any other value replaces the base's."""
    path = robot_path(name_or_path)
    data = _description_data(path, ())
    try:
        return RobotDescription.model_validate(data)
    except ValidationError as exc:
        raise RobotDescriptionError(_format_errors(path, exc)) from None


def _description_data(path: Path, extending: tuple[Path, ...]) -> dict:
    """The fields of the description in ``path``, its ``extends`` chain merged in."""
    if not path.exists():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise RobotDescriptionError(f"{path}: no such robot description (known robots: {known})")
    data = read_yaml(path, RobotDescriptionError)
    if not isinstance(data, dict):
        found = "nothing (an empty file)" if data is None else f"a {type(data).__name__}"
        raise RobotDescriptionError(f"{path}: expected a mapping of fields at the top level, found {found}")
    base = data.pop("extends", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise RobotDescriptionError(f"{path}: extends: expected a robot name or a path, got {base!r}")
    base_path = robot_path(base) if Path(base).suffix not in {".yaml", ".yml"} else path.parent / base
    chain = (*extending, path.resolve())
    if base_path.resolve() in chain:
        raise RobotDescriptionError(f"{path}: extends: {base!r} extends this description again (a cycle)")
    return _merged(_description_data(base_path, chain), data)


def extended(base: RobotDescription, data: dict) -> RobotDescription:
    """``base`` with ``data``'s fields merged in key by key, as a file that ``extends:`` it would be (its own
    ``extends`` is ``base``): the description a fit writes, without writing it."""
    over = {key: value for key, value in data.items() if key != "extends"}
    try:
        return RobotDescription.model_validate(_merged(base.model_dump(mode="json"), over))
    except ValidationError as exc:
        raise RobotDescriptionError(_format_errors(Path(f"{base.name} (extended)"), exc)) from None


def _merged(base: object, over: object) -> object:
    if isinstance(base, dict) and isinstance(over, dict):
        return {**base, **{key: _merged(base.get(key), value) for key, value in over.items()}}
    return over


def _format_errors(path: Path, exc: ValidationError) -> str:
    """Every problem pydantic found, on one line: ``path: field: reason; path: field: reason``."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(part) for part in err["loc"] if not _is_union_tag(part)) or "(top level)"
        lines.append(f"{path}: {loc}: {err['msg']}")
    return "; ".join(lines)


_KINEMATICS_TAGS = {"anthropomorphic", "dh"}


def _is_union_tag(part: object) -> bool:
    """Pydantic puts the tried union member (class name or discriminator tag) into locations; users never
    typed those, so they are left out of the field path."""
    return isinstance(part, str) and (
        part[:1].isupper() or part.startswith("function-") or part in _KINEMATICS_TAGS
    )

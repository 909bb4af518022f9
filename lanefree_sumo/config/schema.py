"""The configuration's schema: every default, unit and allowed value of the platform.

Every number the simulation, the driver model, the rewards, the observations and the algorithms
use lives here, with its unit, and nowhere else (specification §1–§9). Allowed values are ``Literal``
types or a field's ``range`` metadata; :mod:`.validation` checks them. Every section is frozen: a config
changes only by :func:`~.validation.merge_config`, which makes a new one. A run resolves its config once
(:class:`ResolvedConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal, get_args

RoadKind = Literal["ring", "onramp"]


@dataclass(frozen=True)
class OnRampConfig:
    """The open road with an on-ramp (``road.kind: onramp``).

    Laid out after TrafficFluid-Sim's on/off-ramp example: a straight main road ``road.width_m`` wide,
    and beside its right edge an acceleration lane whose last ``merge_m`` are the merge zone, where its
    usable width closes."""

    upstream_m: float = field(default=1000.0, metadata={"range": (50.0, 20_000.0)})
    """Main road before the ramp, where the entering traffic settles (m)."""
    ramp_m: float = field(default=480.0, metadata={"range": (50.0, 5_000.0)})
    """Length of the acceleration lane beside the main road (m)."""
    merge_m: float = field(default=200.0, metadata={"range": (1.0, 5_000.0)})
    """The ramp's last part, where its usable width closes linearly to 0 (m); at most ``ramp_m``."""
    downstream_m: float = field(default=500.0, metadata={"range": (50.0, 20_000.0)})
    """Main road after the ramp; vehicles leave the road at its end (m)."""
    ramp_width_m: float = field(default=3.0, metadata={"range": (2.5, 20.0)})
    """Width of the acceleration lane (m)."""
    main_flow_veh_per_h: float = field(default=2400.0, metadata={"range": (0.0, 14_400.0)})
    """Demand at the main road's upstream end (veh/h; arrivals at random, seeded)."""
    ramp_flow_veh_per_h: float = field(default=300.0, metadata={"range": (0.0, 14_400.0)})
    """Demand at the ramp's start (veh/h; arrivals at random, seeded)."""
    main_entry_speed_mps: float = field(default=25.0, metadata={"range": (0.0, 60.0)})
    """Speed of a vehicle entering the main road (m/s; its desired speed if that is lower)."""
    ramp_entry_speed_mps: float = field(default=20.0, metadata={"range": (0.0, 60.0)})
    """Speed of a vehicle entering the ramp (m/s; its desired speed if that is lower)."""
    merge_lateral_speed_mps: float = field(default=0.5, metadata={"range": (0.0, 5.0)})
    """The lateral speed an unmerged ramp vehicle's target-speed force aims at in the merge zone (m/s;
    elsewhere, and for every other vehicle, 0 as in specification §3): the merge rule's intention to merge."""
    agent_start: Literal["ramp", "main"] = "ramp"
    """Where a learning vehicle starts: at the ramp's start (the merge task) or on the main road at
    ``agent_main_start_m`` (pass the merge area)."""
    agent_main_start_m: float = field(default=700.0, metadata={"range": (5.0, 20_000.0)})
    """x of a learning vehicle's centre when it starts on the main road (m)."""
    entry_headway_s: float = field(default=1.0, metadata={"range": (0.0, 10.0)})
    """An arrival enters only where every vehicle whose band it would overlap keeps at least
    ``spawn.gap_x_m`` + this time × the entry speed of bumper gap; otherwise it waits (s)."""


@dataclass(frozen=True)
class RoadConfig:
    """The road hosted by SUMO: the ring (one lane as wide as the road) or the open road with an on-ramp."""

    kind: RoadKind = "ring"
    """``ring``: the paper's closed ring; ``onramp``: an open road with an on-ramp (``road.onramp``)."""
    length_m: float = field(default=500.0, metadata={"range": (50.0, 10_000.0)})
    """Centre-line length of the closed loop (m); the on-ramp's length comes from ``road.onramp``."""
    width_m: float = field(default=10.2, metadata={"range": (2.5, 100.0)})
    """Road (= lane) width (m): the ring's, and the on-ramp's main road."""
    speed_limit_mps: float = field(default=50.0, metadata={"range": (1.0, 1000.0)})
    """SUMO lane speed limit (m/s); only needs to exceed every commanded speed."""
    onramp: OnRampConfig = field(default_factory=OnRampConfig)

    @property
    def main_length_m(self) -> float:
        """The ring's circumference, or the on-ramp's main road from its upstream to its downstream end (m)."""
        if self.kind == "ring":
            return self.length_m
        o = self.onramp
        return o.upstream_m + o.ramp_m + o.downstream_m


@dataclass(frozen=True)
class SimulationConfig:
    """Time stepping and SUMO options."""

    step_s: float = field(default=0.25, metadata={"range": (0.01, 1.0)})
    """Simulation step T (s)."""
    episode_steps: int = field(default=800, metadata={"range": (1, 10_000_000)})
    """Steps per episode (800 × 0.25 s = 200 s)."""
    lateral_resolution_m: float = field(default=0.8, metadata={"range": (0.01, 10.0)})
    """SUMO ``--lateral-resolution`` (m): switches on the sublane model."""
    edge_clearance_m: float = field(default=1e-3, metadata={"range": (0.0, 1.0)})
    """Body edges are clipped this far inside the road edges (m): SUMO rejects a lateral target
    that puts the body at or past the lane border."""
    edge_contact_tolerance_m: float = field(default=1e-6, metadata={"range": (0.0, 0.1)})
    """A lateral overshoot past the clip line smaller than this is rounding: it is clipped but
    not counted as a boundary contact (m)."""
    sumo_min_lateral_speed_mps: float = field(default=0.001, metadata={"range": (0.0, 1.0)})
    """SUMO treats lateral speeds below this as zero (its NUMERICAL_EPS) and ignores such a
    ``changeSublane``; smaller moves are set with ``setLateralLanePosition`` instead (m/s)."""
    route_loops: int = field(default=400, metadata={"range": (1, 100_000)})
    """How many times the looping route repeats the ring; must exceed the laps of any run."""


@dataclass(frozen=True)
class VehicleClassConfig:
    """Dimensions and desired speeds of one vehicle class."""

    length_m: float = field(metadata={"range": (0.5, 50.0)})
    width_m: float = field(metadata={"range": (0.5, 10.0)})
    desired_speed_min_mps: float = field(metadata={"range": (0.1, 100.0)})
    desired_speed_max_mps: float = field(metadata={"range": (0.1, 100.0)})
    color_rgb: tuple[int, int, int] = field(default=(255, 255, 0), metadata={"range": (0, 255)})
    """Colour in sumo-gui (0–255 each)."""


def _background_class() -> VehicleClassConfig:
    return VehicleClassConfig(3.5, 1.8, 18.0, 22.0, (80, 140, 255))


def _agent_class() -> VehicleClassConfig:
    return VehicleClassConfig(3.2, 1.6, 20.0, 20.0, (0, 200, 0))


@dataclass(frozen=True)
class AccelerationBounds:
    """Acceleration limits (m/s²)."""

    ax_min: float = field(default=-4.5, metadata={"range": (-100.0, 0.0)})
    """Strongest braking (m/s², ≤ 0)."""
    ax_max: float = field(default=2.0, metadata={"range": (0.0, 100.0)})
    """Strongest acceleration (m/s², ≥ 0)."""
    ay_min: float = field(default=-1.8, metadata={"range": (-100.0, 0.0)})
    """Strongest lateral acceleration to the right (m/s², ≤ 0)."""
    ay_max: float = field(default=1.8, metadata={"range": (0.0, 100.0)})
    """Strongest lateral acceleration to the left (m/s², ≥ 0)."""


@dataclass(frozen=True)
class DriverConfig:
    """The force-based lane-free background driver (specification §3, Papageorgiou et al. 2021)."""

    neighbour_range_m: float = field(default=100.0, metadata={"range": (0.1, 10_000.0)})
    """Neighbours j with |dx_j| ≤ this contribute forces (m)."""
    speed_share_ahead: float = field(default=0.30, metadata={"range": (0.0, 1.0)})
    """s_x: approach speed to a vehicle ahead is max(0, vx_i − (1 − s_x)·vx_j) (–)."""
    time_headway_x_s: float = field(default=0.65, metadata={"range": (0.0, 60.0)})
    """τx: longitudinal ramp length L_x = vx_i·τx (s)."""
    time_headway_y_s: float = field(default=0.25, metadata={"range": (0.0, 60.0)})
    """τy: lateral ramp length L_y = uy·τy + ``lateral_ramp_offset_m`` (s)."""
    gain_x: float = field(default=3.0, metadata={"range": (0.01, 100.0)})
    """k_x = c_x with nudging off (the paper's setting): the gain on Σf_x (m/s² per unit force)
    and the braking deceleration c_x in D_x = ux²/(2·c_x) + len (m/s²). The reference uses one
    parameter for both (specification §3)."""
    gain_x_nudging: float = field(default=5.0, metadata={"range": (0.01, 100.0)})
    """k_x = c_x with nudging on (the reference's nudging configuration)."""
    longitudinal_margin_m: float = field(default=2.5, metadata={"range": (0.0, 100.0)})
    """Extra flat part of the longitudinal trapezoid (m)."""
    lateral_ramp_offset_m: float = field(default=0.5, metadata={"range": (0.0, 100.0)})
    """Constant part of L_y (m)."""
    lateral_margin_m: float = field(default=0.5, metadata={"range": (0.0, 100.0)})
    """Extra flat part of the lateral trapezoid beyond the half widths (m)."""
    coef_fy: float = field(default=1.0, metadata={"range": (0.0, 100.0)})
    """Gain on the summed lateral forces Σf_y (m/s² per unit force)."""
    max_repulsions: int = field(default=6, metadata={"range": (1, 1000)})
    """How many repulsions (vehicles ahead) of largest magnitude ``mag`` are summed."""
    nudging: bool = False
    """Whether vehicles behind push forward (nudge). OFF in the paper's training setting."""
    max_nudges: int = field(default=3, metadata={"range": (1, 1000)})
    """How many nudges of largest magnitude ``mag`` are summed when nudging is on."""
    nudge_scale_x: float = field(default=0.9, metadata={"range": (0.0, 100.0)})
    nudge_scale_y: float = field(default=1.0, metadata={"range": (0.0, 100.0)})
    wall_exponent: float = field(default=0.25, metadata={"range": (0.0, 100.0)})
    """x-wall degree δ = |clip(f_x, −1, 1)|^exponent (–)."""
    wall_time_gap_s: float = field(default=0.25, metadata={"range": (0.01, 60.0)})
    """x-wall safe speed v_s = min(gap / this, vx_leader − ``wall_speed_margin_mps``) (s)."""
    wall_speed_margin_mps: float = field(default=0.1, metadata={"range": (0.0, 100.0)})
    edge_decel_mps2: float = field(default=-1.0, metadata={"range": (-100.0, -0.01)})
    """ū of the road-edge bound U(v, d, ū): lateral deceleration assumed available (m/s²); the
    reference's effective (integer) value."""
    edge_speed_factor: float = field(default=1.05, metadata={"range": (0.0, 10.0)})
    """Lateral speed safety factor in the road-edge bound (–)."""
    overspeed_factor: float = field(default=1.2, metadata={"range": (1.0, 10.0)})
    """Longitudinal speed never exceeds this × desired speed (–)."""
    lateral_speed_ratio: float = field(default=0.5, metadata={"range": (0.0, 10.0)})
    """|vy| ≤ this × vx after the step (–)."""
    bounds: AccelerationBounds = field(default_factory=lambda: AccelerationBounds(-4.0, 2.0, -1.0, 1.0))
    """Hard bounds of the background accelerations: the reference declares them as integers, so
    its effective bounds are F_x ∈ [−4, 2], F_y ∈ [−1, 1] m/s² (specification §3)."""

    @property
    def effective_gain_x(self) -> float:
        """k_x = c_x in force: ``gain_x_nudging`` with nudging on, else ``gain_x``."""
        return self.gain_x_nudging if self.nudging else self.gain_x


@dataclass(frozen=True)
class SpawnConfig:
    """Initial placement of vehicles at a density (specification §1).

    The road is cut into cells of (vehicle length + ``gap_x_m``) × (vehicle width + ``gap_y_m``);
    vehicles go to distinct random cells with a random offset inside their cell, so positions
    never overlap and the largest density that fits is known exactly.
    """

    gap_x_m: float = field(default=6.0, metadata={"range": (0.0, 1000.0)})
    """Minimum bumper-to-bumper gap between vehicles of one row (m)."""
    gap_y_m: float = field(default=0.5, metadata={"range": (0.0, 100.0)})
    """Minimum lateral clearance between rows and to the road edges (m)."""
    initial_speed_mps: float = field(default=18.0, metadata={"range": (0.0, 100.0)})
    """Every vehicle starts at this vx (m/s), so no pair starts out closing in (vy = 0)."""


Backend = Literal["libsumo", "traci", "numpy"]
Device = Literal["cpu", "torch-cpu", "cuda"]
ROAD_KINDS: tuple[str, ...] = get_args(RoadKind)
ObservationKind = Literal["vector", "set"]
ActionKind = Literal["continuous", "discrete"]
OvertakeBonus = Literal["every_pass", "once_per_vehicle", "net_passes"]
LearnerProfile = Literal["sb3", "kerasrl"]
RewardPreset = Literal["collision", "overtake_collision", "fields", "fields_collision", "fields_overtake_collision",
                       "zones_overtake_collision", "fields_zones_overtake_collision"]
"""The reward presets of specification §7, the one list of their names; each name lists its components, from
which :data:`lanefree_sumo.rl.rewards.PRESETS` derives the weights."""
AlgorithmName = Literal["ddpg", "td3", "sac", "ppo", "dqn", "ddqn", "dueling", "per"]
"""The algorithms; their classes are :data:`lanefree_sumo.rl.algorithms.ALGORITHMS` (a test keeps the two in
step). The config owns every name it validates: the config room imports nothing from the RL room."""
BACKENDS: tuple[str, ...] = get_args(Backend)
DEVICES: tuple[str, ...] = get_args(Device)
OBSERVATION_KINDS: tuple[str, ...] = get_args(ObservationKind)
ACTION_KINDS: tuple[str, ...] = get_args(ActionKind)


@dataclass(frozen=True)
class ScenarioConfig:
    """What is on the road."""

    density_veh_per_km: float = field(default=70.0, metadata={"range": (1e-9, 1e6)})
    """Background vehicles = round(density · L / 1000) (veh/km)."""
    background: VehicleClassConfig = field(default_factory=_background_class)
    background_fast_color_rgb: tuple[int, int, int] = field(default=(255, 150, 40), metadata={"range": (0, 255)})
    """sumo-gui colour of background vehicles desiring more than the middle desired speed."""
    agent: VehicleClassConfig = field(default_factory=_agent_class)
    with_agent: bool = False
    """Whether externally controlled agent vehicles are on the road."""
    agents: int = field(default=1, metadata={"range": (1, 64)})
    """How many agent vehicles when ``with_agent``: LaneFree-v0 drives one, the multi-agent environment
    (:mod:`lanefree_sumo.rl.multi_agent`, ``lanefree train --agents K``) any number; they come on top of
    the background vehicles of ``density_veh_per_km``."""
    agent_bounds: AccelerationBounds = field(default_factory=AccelerationBounds)
    agent_max_speed_mps: float = field(default=30.0, metadata={
        "range": (1.0, 1000.0), "paper": "none: only the agent's accelerations are bounded"})
    """The agent's top speed (m/s); specification §2 bounds only its accelerations, but without a top
    speed a policy learns to lap the ring at hundreds of m/s and farm overtake bonuses."""
    agent_lateral_speed_ratio: float | None = field(default=None, metadata={
        "range": (0.0, 100.0), "paper": "none for the agent; the background keeps |v_y| <= 0.5 v_x"})
    """The agent's |vy| ≤ this × vx at the end of every step, as ``driver.lateral_speed_ratio`` bounds the
    background's (–); null (the default): no bound."""
    driver: DriverConfig = field(default_factory=DriverConfig)
    spawn: SpawnConfig = field(default_factory=SpawnConfig)


@dataclass(frozen=True)
class RewardConfig:
    """Reward components (specification §7, paper Tables 3–4). Weights are set by the preset."""

    preset: RewardPreset = "fields_zones_overtake_collision"
    """One of the presets of specification §7 (:data:`lanefree_sumo.rl.rewards.PRESETS`)."""
    epsilon_r: float = field(default=0.1, metadata={"range": (1e-9, 1e6)})
    """ε_r of the reciprocal reward (–)."""
    collision_reward: float = field(default=-2.5, metadata={"range": (-1e6, 0.0)})
    """r_c, added on every step the agent overlaps a vehicle."""
    overtake_reward: float = field(default=2.0, metadata={"range": (0.0, 1e6)})
    """r_o, added on a step the agent overtakes and does not collide."""
    overtake_bonus: OvertakeBonus = field(default="every_pass", metadata={
        "paper": "r_o when the agent overtakes a vehicle (which passes count is not said)"})
    """Which passes earn r_o: ``every_pass`` (the default) any pass, the same vehicle again on a later lap too;
    ``once_per_vehicle`` only the first pass of each vehicle in an episode; ``net_passes`` a pass that takes the
    agent's passes minus being passed, for that vehicle, above its highest so far in the episode."""
    field_magnitude: float = field(default=0.5, metadata={"range": (0.0, 1e6)})
    """m_f, peak of each ellipsoid field (–)."""
    critical_exponents: tuple[float, float, float] = field(default=(4.0, 4.0, 1.0), metadata={"range": (0.1, 100.0)})
    """(p_x, p_y, p_t) of the critical region."""
    broad_exponents: tuple[float, float, float] = field(default=(2.0, 2.0, 1.0), metadata={"range": (0.1, 100.0)})
    """(p_x, p_y, p_t) of the broad region."""
    k_r_s_per_m: float = field(default=0.5, metadata={"range": (0.0, 100.0)})
    """Broad-region longitudinal stretch per m/s of closing speed (s/m)."""
    e_v_s_per_m: float = field(default=0.4, metadata={"range": (0.0, 100.0)})
    """Broad-region lateral stretch per m/s of lateral closing speed (s/m)."""
    broad_stretch: Literal["closing", "absolute"] = "closing"
    """What stretches the broad region: ``closing`` (default) the closing speeds only (a receding
    neighbour does not stretch it), ``absolute`` any speed difference |Δvx|, |Δvy| — the other
    reading of the paper's undefined k_r, e_v (docs/results.md's controlled runs compare the two)."""
    zone_time_gap_s: float = field(default=0.7, metadata={"range": (0.0, 60.0)})
    """t_g: zones scan d_o = vx · t_g ahead (s)."""
    zone_margin_m: float = field(default=0.1, metadata={"range": (0.0, 100.0)})
    """A zone must be at least agent width + 2 × this wide (m)."""
    min_desired_speed_mps: float = field(default=1.0, metadata={"range": (0.01, 100.0)})
    """Floor of v_d,eff in c_x (m/s)."""


@dataclass(frozen=True)
class ObservationConfig:
    """Agent observation (specification §5)."""

    kind: ObservationKind = "vector"
    """``vector`` (the paper's n nearest) or ``set`` (all in range, padded)."""
    encoder: Literal["small", "paper"] = "small"
    """Set encoder configuration (``kind = set`` only): ``small`` (the project's default, d1 = d2 = 8)
    or ``paper`` (Liu et al. Table 1 / Alg. 1); see ``lanefree_sumo.rl.encoder.PRESETS``."""
    n_neighbours: int = field(default=5, metadata={"range": (1, 1000)})
    """Nearest vehicles in the vector observation (the paper's 5)."""
    range_m: float = field(default=80.0, metadata={"range": (0.1, 10_000.0)})
    """Observation range: vehicles with |dx| ≤ this are seen (m)."""
    max_rows: int = field(default=32, metadata={"range": (1, 10_000)})
    """Rows of the set observation (padding above the vehicles in range)."""
    scale: bool = True
    """Scale features to O(1); False returns raw SI values."""
    speed_scale_mps: float = field(default=25.0, metadata={"range": (0.01, 1000.0)})
    """Longitudinal speeds (vx, v_d, vx_j) are divided by this when scaling (m/s)."""
    lateral_speed_scale_mps: float = field(default=2.0, metadata={"range": (0.01, 1000.0)})
    """Lateral speeds (vy, vy_j) are divided by this when scaling (m/s)."""
    road_features: bool = True
    """On the on-ramp, 4 more ego features: the boundaries at the front, on the ramp or not, the room to
    the ramp's end. False keeps the ring's 4 ego features, so that a policy trained on the ring can drive
    on the on-ramp (``lanefree evaluate RUN --scenario onramp``)."""


@dataclass(frozen=True)
class ActionConfig:
    """Agent actions (specification §6)."""

    kind: ActionKind = "continuous"
    """``continuous`` (Box(2) in [−1, 1], piecewise linear) or ``discrete`` (9 actions)."""
    discrete_ax_mps2: float = field(default=2.0, metadata={
        "range": (0.0, 100.0), "paper": "9 actions: accelerate, brake, left, right, their combinations, none"})
    """|ax| of the discrete accelerate/brake actions (m/s²)."""
    discrete_ay_mps2: float = field(default=1.0, metadata={
        "range": (0.0, 100.0), "paper": "9 actions (their sizes are not given)"})
    """|ay| of the discrete left/right actions (m/s²)."""


@dataclass(frozen=True)
class EpisodeConfig:
    """Episode handling of the environment."""

    terminate_on_collision: bool = False
    """End the episode when the agent collides (the paper does not: collisions only cost)."""


@dataclass(frozen=True)
class ShieldConfig:
    """The agent's safety shield (:mod:`lanefree_sumo.rl.shield`); off by default."""

    enabled: bool = False
    """Pass every agent action through the shield (``lanefree train/evaluate/rollout --shield``)."""
    intervention_penalty: float = field(default=0.0, metadata={"range": (0.0, 1e6)})
    """Subtracted from the reward on every step the shield changes the action (reward units, ≥ 0)."""
    horizon_s: float = field(default=1.0, metadata={"range": (0.01, 60.0)})
    """Look-ahead for the other vehicles' lateral motion (s): a vehicle whose body could reach the
    agent's committed lateral interval within this time, at its lateral bound, is in the agent's
    corridor. Must be at least one step."""
    margin_x_m: float = field(default=0.5, metadata={"range": (0.0, 100.0)})
    """Bumper gap kept beyond the braking-distance bound to a vehicle ahead (m)."""
    margin_y_m: float = field(default=0.2, metadata={"range": (0.0, 100.0)})
    """Lateral clearance kept beyond another vehicle's reachable lateral extent (m)."""
    lateral_candidates: int = field(default=37, metadata={"range": (2, 10_001)})
    """Evenly spaced lateral accelerations across the agent's bounds that the shield searches
    besides the policy's own (–)."""
    fallback_steers_clear: bool = False
    """When no action is certified: among the least-violating candidates, take those whose committed
    band reaches least deep (m) into the reach of the vehicles ahead whose gap they violate, then the
    one closest to the policy's. Off: the closest among the least-violating, which keeps a policy's
    steering towards a leader it is already too close to (the violation there is the gap's)."""


@dataclass(frozen=True)
class ActorCriticConfig:
    """DDPG (paper Table 1) and the other continuous-action algorithms (TD3, SAC, PPO)."""

    actor_layers: tuple[int, ...] = field(default=(256, 128), metadata={"range": (1, 100_000)})
    """Hidden layers of the actor; output 2 (tanh)."""
    critic_layers: tuple[int, ...] = field(default=(256, 128), metadata={"range": (1, 100_000)})
    """Hidden layers of the critic; output 1."""
    learning_rate: float = field(default=1e-3, metadata={"range": (1e-9, 1.0)})
    batch_size: int = field(default=64, metadata={"range": (1, 1_000_000)})
    gamma: float = field(default=0.98, metadata={"range": (0.0, 1.0)})
    buffer_size: int = field(default=100_000, metadata={"range": (1, 100_000_000)})
    tau: float = field(default=0.001, metadata={"range": (1e-9, 1.0)})
    """Soft target update rate (DDPG/TD3/SAC)."""
    learning_starts_steps: int = field(default=800, metadata={"range": (0, 100_000_000)})
    """Steps before the first update (one episode)."""
    warmup_actions: Literal["uniform", "policy"] = field(default="uniform", metadata={
        "paper": "not said (Keras-RL's DDPG acts with its actor and noise from the first step)"})
    """What DDPG does before ``learning_starts_steps``: ``uniform`` random actions (SB3) or ``policy`` (its
    untrained actor with the exploration noise, as Keras-RL's DDPG)."""
    pre_tanh_penalty: float = field(default=0.0, metadata={
        "range": (0.0, 1e6),
        "paper": "not in either paper (neither says how DDPG's actor was kept off its tanh bound)"})
    """λ of the term λ·mean(u²) added to DDPG's actor loss, u the actor's output before its tanh (–): keeps u
    where tanh' does not vanish, so the critic's gradient still reaches the actor; 0 (default): SB3's loss.
    DDPG only (:mod:`lanefree_sumo.rl.algorithms.batched.ddpg`)."""
    ou_sigma: float = field(default=0.2, metadata={"range": (0.0, 100.0)})
    """Ornstein–Uhlenbeck exploration noise σ (action units; the paper does not give it)."""
    ou_theta: float = field(default=0.15, metadata={"range": (0.0, 100.0)})
    """Ornstein–Uhlenbeck mean reversion θ per unit time (SB3's OU process with its dt = 0.01, so
    0.0015 per step; the paper gives no value)."""
    ppo_n_steps: int = field(default=800, metadata={"range": (2, 10_000_000)})
    """PPO rollout length per environment (steps)."""


@dataclass(frozen=True)
class DQNConfig:
    """The DQN family (paper Table 1 and §4.1)."""

    layers: tuple[int, ...] = field(default=(128, 64), metadata={"range": (1, 100_000)})
    """Hidden layers; output 9 Q-values."""
    learning_rate: float = field(default=1e-3, metadata={"range": (1e-9, 1.0)})
    batch_size: int = field(default=64, metadata={"range": (1, 1_000_000)})
    gamma: float = field(default=0.98, metadata={"range": (0.0, 1.0)})
    buffer_size: int = field(default=50_000, metadata={"range": (1, 100_000_000)})
    epsilon_start: float = field(default=1.0, metadata={"range": (0.0, 1.0)})
    epsilon_end: float = field(default=0.1, metadata={"range": (0.0, 1.0)})
    epsilon_decay_episodes: int = field(default=200, metadata={"range": (1, 10_000_000)})
    """ε falls linearly from start to end over this many episodes, then stays."""
    target_update_steps: int = field(default=10_000, metadata={"range": (1, 100_000_000)})
    """Hard target-network update interval (steps; one gradient update per step, so also updates). The paper
    does not give it. 10 000 is the Nature DQN's convention (Mnih et al. 2015: every 10 000 parameter
    updates), which the paper's double-DQN reference [19] takes over (its tuned double DQN uses 30 000),
    and SB3's default (there counted in environment steps). See docs/interpretation.md."""
    learning_starts_steps: int = field(default=800, metadata={"range": (0, 100_000_000)})
    """Steps before the first update (ε-greedy from ``epsilon_start`` meanwhile)."""
    loss: Literal["huber", "squared"] = field(default="huber", metadata={
        "paper": "not said (Keras-RL's default: the squared error)"})
    """TD loss: ``huber`` (SB3's smooth L1, β = 1) or ``squared`` (½·δ², Keras-RL's with ``delta_clip = inf``);
    the two agree for |δ| < 1."""
    max_grad_norm: float | None = field(default=10.0, metadata={
        "range": (1e-9, 1e9), "paper": "not said (Keras-RL clips no gradient)"})
    """Clip the gradient's global norm at this (SB3's default 10); null: no clip."""


@dataclass(frozen=True)
class TrainConfig:
    """A training run (specification §9)."""

    algo: AlgorithmName = "ddpg"
    """A name of the algorithm registry (:data:`lanefree_sumo.rl.algorithms.ALGORITHMS`)."""
    profile: LearnerProfile = field(default="sb3", metadata={"paper": "the agents were built with Keras-RL"})
    """The learner choices the paper leaves open, set together (:data:`LEARNER_PROFILES`): ``sb3`` (SB3's
    defaults) or ``kerasrl`` (Keras-RL's DQNAgent and DDPGAgent defaults); keys given beside it win."""
    episodes: int = field(default=625, metadata={"range": (1, 10_000_000)})
    """Training episodes of ``sim.episode_steps`` steps each."""
    envs: int = field(default=1, metadata={"range": (1, 4096)})
    """Environments one policy learns from at once (SB3's ``n_envs``): stepped in this process by the one trainer
    (the batchable algorithms, on the numpy backend: libsumo runs one simulation per process), one process each
    in SB3's loop (SAC, PPO)."""
    checkpoint_every_episodes: int = field(default=25, metadata={"range": (1, 10_000_000)})
    """Save a checkpoint every this many episodes."""
    torch_threads: int = field(default=1, metadata={"range": (1, 1024)})
    """CPU threads for torch; the networks are small, and more threads only contend with SUMO."""
    backend: Backend = "numpy"
    """Simulation backend of training runs, copied to the run's ``backend``: ``numpy`` (default) gives the
    same episodes as ``libsumo`` bit for bit without SUMO (``tests/sim/test_sumo.py``,
    ``tests/experiments/test_golden_runs.py``), ~2.6× faster; ``libsumo``/``traci`` train inside SUMO.
    Evaluation, rollout and replay of the run can use any backend."""
    device: Device = "cpu"
    """Where batched training (``train --seeds``, a sweep's batches, and a single run the batched path trains:
    DDPG, TD3, the DQN family on the ring) keeps the simulation and the learners: ``cpu`` (the numpy simulation),
    ``cuda`` (the same functions as torch on the GPU, float64, the networks float32; each iteration one CUDA graph,
    the random numbers drawn on the GPU, so equal to the CPU's runs in distribution, not bit for bit) or
    ``torch-cpu`` (the torch simulation and learners on the CPU, in the host's loop: slower than ``cpu``, for
    checking the torch path without a GPU). The
    shield, the on-ramp, a run inside SUMO, runs of several agents or environments and runs of SB3's loop (SAC,
    PPO) train on the CPU (``cpu``)."""
    actor_critic: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    dqn: DQNConfig = field(default_factory=DQNConfig)


LEARNER_PROFILES: dict[str, dict[str, Any]] = {
    "sb3": {"train": {"dqn": {"loss": "huber", "max_grad_norm": 10.0, "learning_starts_steps": 800},
                      "actor_critic": {"warmup_actions": "uniform", "learning_starts_steps": 800}}},
    "kerasrl": {"train": {"dqn": {"loss": "squared", "max_grad_norm": None, "learning_starts_steps": 1000},
                          "actor_critic": {"warmup_actions": "policy", "learning_starts_steps": 1000}}},
}
"""What each ``train.profile`` sets: SB3's defaults, or Keras-RL's (``DQNAgent``: ``delta_clip = inf``, so the
loss is ½·δ², no gradient clip, ``nb_steps_warmup = 1000``; ``DDPGAgent``: the actor with its random process
from the first step, ``nb_steps_warmup_critic = nb_steps_warmup_actor = 1000``). The paper's own values (γ,
batch size, learning rate, layers, ε schedule) are not part of a profile."""


@dataclass(frozen=True)
class LaneFreeConfig:
    """Everything: road, simulation, scenario, rewards, observations."""

    road: RoadConfig = field(default_factory=RoadConfig)
    sim: SimulationConfig = field(default_factory=SimulationConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    action: ActionConfig = field(default_factory=ActionConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    seed: int = field(default=0, metadata={"range": (0, 2**31 - 1)})
    """Random seed of traffic and networks; SUMO takes 0 … 2³¹ − 1."""
    backend: Backend = "libsumo"
    """``libsumo`` (fast, default), ``traci`` (socket; needed for the GUI) or ``numpy`` (no SUMO)."""
    gui: bool = False
    """Open sumo-gui (forces the TraCI backend)."""
    net_file: str = ""
    """SUMO network; empty = the committed ring for ``road`` (generated on demand)."""

    @property
    def background_vehicles(self) -> int:
        """round(density · L / 1000): on the ring, and at the start on the on-ramp's main road."""
        return int(round(self.scenario.density_veh_per_km * self.road.main_length_m / 1000.0))


@dataclass(frozen=True)
class ResolvedConfig(LaneFreeConfig):
    """A run's config resolved once, at the top of the run: validated whole, with what the run derives fixed
    in it (the agent on the road; for training, the algorithm's action kind and the backend). Made only by
    :func:`lanefree_sumo.rl.env.resolve_config` (and :func:`lanefree_sumo.rl.models.training_config`, through it);
    the environments, the simulation and the learners take it as it is — also in a worker process, which
    receives it pickled. Change a value with :func:`~.validation.merge_config`, which gives a plain
    :class:`LaneFreeConfig` again, to be resolved anew (``dataclasses.replace`` would keep the mark)."""

    @classmethod
    def of(cls, cfg: LaneFreeConfig) -> ResolvedConfig:
        """``cfg``'s values, marked resolved (the last step of a resolution; ``cfg`` validated whole)."""
        return cls(**{f.name: getattr(cfg, f.name) for f in fields(cfg)})

    def unresolved(self) -> LaneFreeConfig:
        """The same values as a plain :class:`LaneFreeConfig`."""
        return LaneFreeConfig(**{f.name: getattr(self, f.name) for f in fields(self)})


@dataclass(frozen=True)
class EvaluationConfig:
    """Defaults of ``lanefree evaluate`` (not part of a run's config)."""

    episodes: int = 20
    """Evaluation episodes, deterministic, on fresh seeds."""
    seed_offset: int = 100_000
    """Evaluation episode k of a run with seed s uses seed s + this + k: never a training seed."""


@dataclass(frozen=True)
class ReplayConfig:
    """Defaults of ``lanefree replay`` in sumo-gui. Vehicle colours come from the scenario."""

    delay_s: float = 0.05
    """Wall-clock delay per step (s)."""
    zoom_percent: float = 400.0
    """View zoom on the ring (%; 100 fits the whole network into the view)."""
    onramp_zoom_percent: float = 2000.0
    """View zoom on the on-ramp (%): its network spans ~2.2 km, so this shows ~110 m around the agent."""
    size_px: tuple[int, int] = (1024, 768)
    """View size, width × height (pixels)."""
    collision_color_rgb: tuple[int, int, int] = (255, 0, 0)
    """Colour of vehicles while they overlap another (0–255 each)."""
    shield_color_rgb: tuple[int, int, int] = (230, 0, 230)
    """Colour of the agent on the steps the safety shield changed its action (0–255 each)."""
    display_timeout_s: float = 60.0
    """How long sumo-gui may take to open its window before replay or ``simulate --gui`` gives up (s); a sumo-gui
    that exits (no such display) is reported at once. A loaded machine can take over 10 s to open it."""


@dataclass(frozen=True)
class ReportConfig:
    """Defaults of ``lanefree report``."""

    last_episodes: int = 50
    """Episodes at the end of each run averaged in the tables (the paper's 50)."""
    smooth_episodes: int = 20
    """Trailing moving-average window of the learning curves (episodes)."""

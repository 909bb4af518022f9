"""One typed, nested configuration for the whole platform (``from lanefree_sumo.config import …``).

:mod:`.schema` holds every default, unit and allowed value; :mod:`.validation` merges dict
overrides and validates every value in one place.
"""

from lanefree_sumo.config.schema import (
    ACTION_KINDS,
    BACKENDS,
    DEVICES,
    OBSERVATION_KINDS,
    ROAD_KINDS,
    AccelerationBounds,
    ActionConfig,
    ActionKind,
    ActorCriticConfig,
    AlgorithmName,
    Backend,
    DQNConfig,
    DriverConfig,
    EpisodeConfig,
    EvaluationConfig,
    LaneFreeConfig,
    ObservationConfig,
    ObservationKind,
    OnRampConfig,
    ReplayConfig,
    ReportConfig,
    ResolvedConfig,
    RewardConfig,
    RewardPreset,
    RoadConfig,
    ScenarioConfig,
    ShieldConfig,
    SimulationConfig,
    SpawnConfig,
    TrainConfig,
    VehicleClassConfig,
)
from lanefree_sumo.config.validation import (
    ADDED_LATER,
    RETIRED,
    SAME_RESULTS,
    check_value,
    config_differences,
    config_to_dict,
    drop_retired,
    layered_config,
    merge_config,
    missing_keys,
    nested_overrides,
    read_config_file,
    validate_config,
    validate_density,
)
from lanefree_sumo.errors import ConfigError

__all__ = [
    "ACTION_KINDS", "ADDED_LATER", "BACKENDS", "DEVICES", "OBSERVATION_KINDS", "RETIRED", "ROAD_KINDS", "SAME_RESULTS",
    "AccelerationBounds", "ActionConfig", "ActionKind", "ActorCriticConfig", "AlgorithmName", "Backend", "ConfigError",
    "DQNConfig", "DriverConfig", "EpisodeConfig", "EvaluationConfig", "LaneFreeConfig", "ObservationConfig",
    "ObservationKind", "OnRampConfig",
    "ReplayConfig", "ReportConfig", "ResolvedConfig", "RewardConfig", "RewardPreset", "RoadConfig", "ScenarioConfig",
    "ShieldConfig",
    "SimulationConfig", "SpawnConfig", "TrainConfig", "VehicleClassConfig", "check_value", "config_differences",
    "config_to_dict", "drop_retired", "layered_config", "merge_config", "missing_keys", "nested_overrides",
    "read_config_file",
    "validate_config", "validate_density",
]

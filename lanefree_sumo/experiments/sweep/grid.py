"""Grids of training runs: the built-in grid files (the paper's tables, the second paper's comparison) or
a YAML file.

A grid is a list of *settings* (algorithm, reward preset, density in veh/km) × a list of seeds,
with an episode budget and config overrides applied to every run. The built-in grids are the YAML
files of :data:`GRIDS_DIR`, each selected by its file name: ``table5`` … ``table8`` (the settings of
that table of :data:`~lanefree_sumo.experiments.analysis.paper.PAPER_ROWS`), ``paper`` (their union, each
setting once) and ``varobs`` (the variable-size observation through the set encoder against the fixed
vector), each with the paper's 10 seeds and 625 episodes. A YAML grid::

    algorithms: [ddpg]                 # registered algorithms (default [ddpg])
    reward_presets: [collision, fields_collision]
    densities: [70, 120]               # veh/km (default [70])
    # or, instead of the three keys above:
    # tables: [5, 6, 7, 8]             # the settings of these tables of the paper, each once
    seeds: [0, 1, 2]                   # or  n_seeds: 10  (seeds 0 … 9; the default)
    episodes: 625                      # optional budget override, default the paper's
    overrides: {}                      # optional config overrides applied to every run
    variants:                          # optional: every setting once per variant, each a mapping of
      default: {}                      #   dotted config keys applied after ``overrides``
      cap25: {scenario.agent_max_speed_mps: 25}
      once_per_car: {reward.overtake_bonus: once_per_vehicle}
    compare: [cap25]                   # optional: variants set against ``default`` over every source in
                                       #   verdict.md (training windows and each evaluation)

A variant's runs are named ``<algo>_<preset>_d<density>_<variant>_s<seed>``; summaries, curves and claims
group by variant (the claims on the variant named ``default``, or on a grid without variants).

Every problem is a :class:`~lanefree_sumo.errors.ConfigError` of one line naming the key.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

from lanefree_sumo.config import LaneFreeConfig, config_to_dict, merge_config, validate_density
from lanefree_sumo.config.validation import read_yaml_file
from lanefree_sumo.errors import ConfigError, UsageError
from lanefree_sumo.experiments.analysis.paper import PAPER_ROWS

PAPER_EPISODES = 625
"""Training episodes per run in the paper (specification §9)."""
PAPER_SEEDS = 10
"""Runs per setting in the paper (specification §10)."""
PAPER_EPISODE_STEPS = LaneFreeConfig().sim.episode_steps
"""Steps per episode in the paper (800 × 0.25 s)."""

TABLES: tuple[int, ...] = tuple(sorted({row[0] for row in PAPER_ROWS}))
GRIDS_DIR = Path(__file__).with_name("grids")
"""The built-in grid files: ``<name>.yaml`` is the grid ``<name>``; its first comment line says what it is."""
BUILTIN_GRIDS: tuple[str, ...] = tuple(sorted(path.stem for path in GRIDS_DIR.glob("*.yaml")))
"""The names of the built-in grids (the files of :data:`GRIDS_DIR`)."""
GRID_KEYS: tuple[str, ...] = ("algorithms", "reward_presets", "densities", "tables", "seeds", "n_seeds", "episodes",
                              "overrides", "variants", "compare")
"""Keys a YAML grid may have."""
SETTING_KEYS: tuple[str, ...] = ("algorithms", "reward_presets", "densities")
"""The keys ``tables`` stands for."""
GRID_OWNED: tuple[str, ...] = ("seed", "train.algo", "reward.preset", "scenario.density_veh_per_km",
                               "train.episodes")
"""Config keys the grid itself sets per run; ``overrides`` may not set them."""
MAX_SEEDS = 10_000
"""The most seeds per setting a grid holds (``n_seeds``, ``seeds``, ``--seeds``)."""


def _seeds_bound(count: int) -> str:
    """The one line for ``--seeds count`` outside 1 … :data:`MAX_SEEDS`."""
    return f"--seeds {count}: a sweep trains 1 to {MAX_SEEDS} seeds per setting"


DEFAULT_VARIANT = "default"
"""The variant whose runs the paper's claims are checked on (a grid without variants has one, named "")."""
VARIANT_NAME = re.compile(r"[a-z0-9][a-z0-9_]{0,39}")


class Setting(NamedTuple):
    """One row of a results table: algorithm, reward preset, density (veh/km) and the grid's variant
    ("" in a grid without variants)."""

    algorithm: str
    preset: str
    density: float
    variant: str = ""

    @property
    def label(self) -> str:
        return f"{self.algorithm} / {self.preset} / d{self.density:g}" + (f" / {self.variant}" if self.variant else "")

    @property
    def tables(self) -> tuple[int, ...]:
        """The paper's tables that report this setting (empty when none does)."""
        return tuple(sorted({t for t, a, p, d, _, _ in PAPER_ROWS
                             if (a, p, round(float(d), 6)) == (self.algorithm, self.preset, self.density)}))


class Cell(NamedTuple):
    """One run of a grid: a setting and a seed."""

    setting: Setting
    seed: int

    @property
    def name(self) -> str:
        """The run folder's name: ``<algo>_<preset>_d<density>_s<seed>``."""
        s = self.setting
        return f"{s.algorithm}_{s.preset}_d{s.density:g}" + (f"_{s.variant}" if s.variant else "") + f"_s{self.seed}"


def make_setting(algorithm: str, preset: str, density: float, variant: str = "") -> Setting:
    return Setting(algorithm, preset, round(float(density), 6), variant)


@dataclass(frozen=True)
class Grid:
    """A resolved grid: what every run of a sweep is."""

    name: str
    settings: tuple[Setting, ...]
    seeds: tuple[int, ...]
    episodes: int = PAPER_EPISODES
    overrides: dict[str, Any] = field(default_factory=dict)
    """Config overrides (nested mapping) applied to every run before the grid's own keys."""
    variants: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Variant name → config overrides (nested mapping) applied after ``overrides``; every setting is in the
    grid once per variant (empty: no variants)."""
    compare: tuple[str, ...] = ()
    """Variants set against :data:`DEFAULT_VARIANT` over every source (training windows and each evaluation)
    in the summary's ``verdict.md``."""

    def variant_overrides(self, setting: Setting) -> dict[str, Any]:
        """The overrides of ``setting``'s variant (none for "")."""
        return self.variants.get(setting.variant, {})

    def cells(self) -> tuple[Cell, ...]:
        """Every run, seed-major: the first seed of every setting first, so that each setting has
        results early."""
        return tuple(Cell(s, seed) for seed in self.seeds for s in self.settings)

    def config(self, cell: Cell) -> LaneFreeConfig:
        """The full training config of ``cell`` (what its run folder's config.yaml must hold)."""
        from lanefree_sumo.rl.models import training_config

        s = cell.setting
        cfg = merge_config(merge_config(merge_config(LaneFreeConfig(), self.overrides),
                                        self.variant_overrides(s)), {
            "seed": cell.seed, "reward": {"preset": s.preset}, "scenario": {"density_veh_per_km": s.density},
            "train": {"algo": s.algorithm, "episodes": self.episodes},
        })
        return training_config(cfg)

    def on_cuda(self) -> bool:
        """Whether any run trains on a CUDA GPU (``train.device = cuda``)."""
        return any(self.config(c).train.device == "cuda" for c in self.cells())

    def road(self, setting: Setting) -> str:
        """The road ``setting``'s runs drive on (``road.kind`` after the overrides and its variant's)."""
        return str(merge_config(merge_config(LaneFreeConfig(), self.overrides), self.variant_overrides(setting))
                   .road.kind)

    @property
    def episode_steps(self) -> int:
        return int(self.overrides.get("sim", {}).get("episode_steps", PAPER_EPISODE_STEPS))

    def budget(self) -> dict[str, Any]:
        """The budget against the paper's, for the manifest and every report."""
        notes = []
        if self.episodes != PAPER_EPISODES:
            notes.append(f"{self.episodes} episodes per run instead of the paper's {PAPER_EPISODES}")
        if len(self.seeds) != PAPER_SEEDS:
            notes.append(f"{len(self.seeds)} seed(s) per setting instead of the paper's {PAPER_SEEDS}")
        if self.episode_steps != PAPER_EPISODE_STEPS:
            notes.append(f"episodes of {self.episode_steps} steps instead of the paper's {PAPER_EPISODE_STEPS}")
        reduced = (self.episodes < PAPER_EPISODES or len(self.seeds) < PAPER_SEEDS
                   or self.episode_steps < PAPER_EPISODE_STEPS)
        return {"episodes": self.episodes, "paper_episodes": PAPER_EPISODES, "seeds": len(self.seeds),
                "paper_seeds": PAPER_SEEDS, "episode_steps": self.episode_steps,
                "paper_episode_steps": PAPER_EPISODE_STEPS, "reduced": reduced, "notes": notes}

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "settings": [{"algorithm": s.algorithm, "reward_preset": s.preset, "density": s.density,
                          **({"variant": s.variant} if s.variant else {}), "tables": list(s.tables)}
                         for s in self.settings],
            "seeds": list(self.seeds),
            "episodes": self.episodes,
            "overrides": self.overrides,
            **({"variants": self.variants} if self.variants else {}),
            **({"compare": list(self.compare)} if self.compare else {}),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str) -> Grid:
        """The grid saved by :meth:`to_dict` (in a manifest); ConfigError naming what is wrong."""
        try:
            settings = tuple(make_setting(str(s["algorithm"]), str(s["reward_preset"]), float(s["density"]),
                                          str(s.get("variant", ""))) for s in data["settings"])
            grid = cls(str(data["name"]), settings, tuple(int(x) for x in data["seeds"]), int(data["episodes"]),
                       dict(data.get("overrides") or {}), {str(k): dict(v) for k, v in
                                                           (data.get("variants") or {}).items()},
                       tuple(str(v) for v in data.get("compare") or ()))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: the grid is unreadable ({type(exc).__name__}: {exc})") from None
        return validate_grid(grid, source)

    def with_budget(self, seeds: int | None = None, episodes: int | None = None,
                    episode_steps: int | None = None, settings: Mapping[str, Any] | None = None) -> Grid:
        """The grid with ``--seeds N`` (seeds 0 … N−1), ``--episodes N``, ``--episode-steps N`` and the
        ``--set`` ``settings`` (nested overrides) merged into its overrides."""
        if seeds is not None and not 1 <= seeds <= MAX_SEEDS:
            raise ConfigError(_seeds_bound(seeds))
        overrides = _merged(self.overrides, settings or {})
        if episode_steps is not None:
            overrides.setdefault("sim", {})["episode_steps"] = episode_steps
        grid = Grid(self.name, self.settings, tuple(range(seeds)) if seeds is not None else self.seeds,
                    episodes if episodes is not None else self.episodes, overrides, self.variants, self.compare)
        return validate_grid(grid, "command line")

    def with_more_seeds(self, count: int, where: str) -> Grid:
        """The grid with new seeds (the smallest unused ones) added until it has ``count``;
        UsageError if it already has more."""
        if count < len(self.seeds):
            raise UsageError(f"{where} has {len(self.seeds)} seeds per setting; --seeds with --resume only adds "
                             f"seeds (give N ≥ {len(self.seeds)})")
        if count > MAX_SEEDS:
            raise UsageError(_seeds_bound(count))
        seeds = list(self.seeds)
        candidate = 0
        while len(seeds) < count:
            if candidate not in seeds:
                seeds.append(candidate)
            candidate += 1
        return replace(self, seeds=tuple(seeds))


def _merged(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``extra`` merged in recursively (copies; ``extra`` wins)."""
    out = {k: _merged(v, {}) if isinstance(v, Mapping) else v for k, v in base.items()}
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merged(out[key], value)
        else:
            out[key] = _merged(value, {}) if isinstance(value, Mapping) else value
    return out


# -- built-in grids -------------------------------------------------------------------------------

def builtin_grid(name: str) -> Grid:
    """The built-in grid ``name`` (the file ``GRIDS_DIR/<name>.yaml``)."""
    if name not in BUILTIN_GRIDS:
        raise ConfigError(f"unknown grid '{name}'; use one of {', '.join(BUILTIN_GRIDS)} or a YAML file")
    return _grid_file(GRIDS_DIR / f"{name}.yaml")


def builtin_descriptions() -> dict[str, str]:
    """Built-in grid name → what it is (the first comment line of its file, without the ``#``)."""
    out = {}
    for name in BUILTIN_GRIDS:
        first = (GRIDS_DIR / f"{name}.yaml").read_text(encoding="utf-8").splitlines()[0]
        out[name] = first.removeprefix("#").strip()
    return out


def load_grid(spec: str | Path) -> Grid:
    """A built-in grid by name, else a YAML grid file."""
    text = str(spec)
    if text in BUILTIN_GRIDS:
        return builtin_grid(text)
    path = Path(spec)
    if not path.is_file():
        raise ConfigError(f"unknown grid '{text}': neither a built-in grid ({', '.join(BUILTIN_GRIDS)}) "
                          "nor a YAML file")
    return _grid_file(path)


def _grid_file(path: Path) -> Grid:
    """The grid of the YAML file ``path``, named after the file."""
    return parse_grid(read_yaml_file(path, "grid file"), path.stem, str(path))


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [value]


def _whole(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _names(where: str, values: Any, allowed: tuple[str, ...], what: str) -> list[str]:
    items = _as_list(values)
    if not items:
        raise ConfigError(f"{where} is empty; give at least one {what}")
    article = "an" if what[0] in "aeiou" else "a"
    for item in items:
        if not isinstance(item, str) or item not in allowed:
            raise ConfigError(f"{where}: {item!r} is not {article} {what}; choose from {', '.join(allowed)}")
    if len(set(items)) < len(items):
        raise ConfigError(f"{where} lists {article} {what} twice")
    return items


def parse_grid(data: Any, name: str, source: str) -> Grid:
    """A grid from the mapping of a YAML grid file; ConfigError of one line naming the bad key."""
    where = f"grid {source}"
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping with keys {', '.join(GRID_KEYS)}")
    for key in data:
        if key not in GRID_KEYS:
            raise ConfigError(f"{where}: unknown key '{key}'; allowed keys: {', '.join(GRID_KEYS)}")
    cells = _cells(where, data)
    if "seeds" in data and "n_seeds" in data:
        raise ConfigError(f"{where}: give either 'seeds' or 'n_seeds', not both")
    if "seeds" in data:
        seeds = _as_list(data["seeds"])
        bad = [s for s in seeds if not _whole(s) or s < 0]
        if not seeds or bad or len(set(seeds)) < len(seeds):
            raise ConfigError(f"{where}: seeds must be distinct whole numbers ≥ 0, got {data['seeds']!r}")
    else:
        n = data.get("n_seeds", PAPER_SEEDS)
        if not _whole(n) or not 1 <= n <= MAX_SEEDS:
            raise ConfigError(f"{where}: n_seeds must be a whole number from 1 to {MAX_SEEDS}, got {n!r}")
        seeds = list(range(n))
    episodes = data.get("episodes", PAPER_EPISODES)
    if not _whole(episodes) or episodes < 1:
        raise ConfigError(f"{where}: episodes must be a whole number ≥ 1, got {episodes!r}")
    overrides = data.get("overrides") or {}
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"{where}: overrides must be a mapping of config keys (e.g. overrides: {{sim: "
                          f"{{episode_steps: 400}}}}), got {overrides!r}")
    variants = _variants(where, data.get("variants"))
    compare = _compare(where, data.get("compare"), variants)
    settings = tuple(make_setting(a, p, d, v) for v in (variants or [""]) for a, p, d in cells)
    return validate_grid(Grid(name, settings, tuple(seeds), episodes, dict(overrides), variants, compare), source)


def _cells(where: str, data: Mapping[str, Any]) -> list[tuple[str, str, float]]:
    """(algorithm, preset, density) of every setting: the paper's ``tables``, or algorithms × reward_presets ×
    densities."""
    from lanefree_sumo.rl.algorithms import ALGORITHM_NAMES
    from lanefree_sumo.rl.rewards import PRESETS

    if "tables" in data:
        given = [key for key in SETTING_KEYS if key in data]
        if given:
            raise ConfigError(f"{where}: give either 'tables' or {', '.join(SETTING_KEYS)}, not both "
                              f"('{given[0]}' is given too)")
        tables = _as_list(data["tables"])
        if not tables or any(not _whole(t) or t not in TABLES for t in tables) or len(set(tables)) < len(tables):
            raise ConfigError(f"{where}: tables must list distinct tables of the paper "
                              f"({', '.join(map(str, TABLES))}), got {data['tables']!r}")
        return list(dict.fromkeys((a, p, float(d)) for t, a, p, d, _, _ in PAPER_ROWS if t in tables))
    if "reward_presets" not in data:
        raise ConfigError(f"{where}: key 'reward_presets' is missing; list the reward presets to train "
                          "(or the paper's 'tables')")
    algorithms = _names(f"{where}: algorithms", data.get("algorithms", ["ddpg"]), ALGORITHM_NAMES, "algorithm")
    presets = _names(f"{where}: reward_presets", data["reward_presets"], tuple(PRESETS), "reward preset")
    densities = []
    for d in _as_list(data.get("densities", [70])):
        try:
            if isinstance(d, bool):
                raise ConfigError(f"density must be a number in veh/km, got {d!r}")
            densities.append(validate_density(d))
        except ConfigError as exc:
            raise ConfigError(f"{where}: densities: {exc}") from None
    if not densities or len(set(densities)) < len(densities):
        raise ConfigError(f"{where}: densities must list at least one density, each once")
    return [(a, p, d) for a in algorithms for p in presets for d in densities]


def _compare(where: str, data: Any, variants: Mapping[str, Any]) -> tuple[str, ...]:
    """``compare``: variants of the grid other than :data:`DEFAULT_VARIANT`, each once."""
    if data is None:
        return ()
    names = _as_list(data)
    if DEFAULT_VARIANT not in variants:
        raise ConfigError(f"{where}: compare sets variants against the variant '{DEFAULT_VARIANT}'; name one in "
                          "variants")
    allowed = tuple(v for v in variants if v != DEFAULT_VARIANT)
    return tuple(_names(f"{where}: compare", names, allowed, "variant other than 'default'"))


def _variants(where: str, data: Any) -> dict[str, dict[str, Any]]:
    """``variants``: name → nested overrides from its mapping of dotted config keys (checked by
    :func:`validate_grid`)."""
    from lanefree_sumo.config import nested_overrides

    if data is None:
        return {}
    if not isinstance(data, Mapping) or not data:
        raise ConfigError(f"{where}: variants must be a mapping of variant names to mappings of dotted config keys")
    out: dict[str, dict[str, Any]] = {}
    for name, keys in data.items():
        if not isinstance(name, str) or not VARIANT_NAME.fullmatch(name):
            raise ConfigError(f"{where}: variant name {name!r} must be 1-40 lower-case letters, digits or _")
        if keys is None:
            keys = {}
        if not isinstance(keys, Mapping) or not all(isinstance(k, str) for k in keys):
            raise ConfigError(f"{where}: variants.{name} must be a mapping of dotted config keys to values")
        out[name] = nested_overrides(list(keys.items()))
    return out


def _owned(overrides: Mapping[str, Any], path: str = "") -> list[str]:
    found = []
    for key, value in overrides.items():
        where = f"{path}.{key}" if path else str(key)
        if where in GRID_OWNED:
            found.append(where)
        elif isinstance(value, Mapping):
            found += _owned(value, where)
    return found


def _check_budget(grid: Grid, where: str) -> None:
    """The grid has runs, at most :data:`MAX_SEEDS` seeds per setting, and episodes to train."""
    if not grid.settings or not grid.seeds:
        raise ConfigError(f"{where}: the grid has no runs")
    if len(grid.seeds) > MAX_SEEDS:
        raise ConfigError(f"{where}: {len(grid.seeds)} seeds per setting; a sweep trains at most {MAX_SEEDS}")
    if grid.episodes < 1:
        raise ConfigError(f"{where}: episodes must be ≥ 1, got {grid.episodes}")


def validate_grid(grid: Grid, source: str) -> Grid:
    """Check the overrides and that every setting's traffic fits on the road (before any run starts)."""
    from lanefree_sumo.rl.models import check_trainable
    from lanefree_sumo.sim.spawn import check_fits

    where = f"grid {source}"
    if not isinstance(grid.overrides, Mapping):
        raise ConfigError(f"{where}: overrides must be a mapping of config keys, got {grid.overrides!r}")
    scenario = grid.overrides.get("scenario")
    agents = scenario.get("agents", 1) if isinstance(scenario, Mapping) else 1
    if agents != 1:
        raise ConfigError(f"{where}: overrides.scenario.agents = {agents!r}: sweeps train one learning vehicle per run "
                          "in this version (use lanefree train --agents K)")
    for label, overrides in (("overrides", grid.overrides),
                             *((f"variants.{name}", keys) for name, keys in grid.variants.items())):
        owned = _owned(overrides)
        if owned:
            raise ConfigError(f"{where}: {label}.{owned[0]} is set by the grid itself "
                              "(use algorithms, reward_presets, densities, seeds or episodes)")
    for name, keys in grid.variants.items():
        try:
            merge_config(merge_config(LaneFreeConfig(), grid.overrides), keys)
        except ConfigError as exc:
            raise ConfigError(f"{where}: variants.{name}: {exc}") from None
    _check_budget(grid, where)
    try:
        base = merge_config(LaneFreeConfig(), grid.overrides)
    except ConfigError as exc:
        raise ConfigError(f"{where}: overrides: {exc}") from None
    folders: dict[str, Setting] = {}
    for setting in grid.settings:  # distinct values the run folder names (or the rounding) cannot tell apart
        name = Cell(setting, grid.seeds[0]).name
        if name in folders:
            raise ConfigError(f"{where}: {folders[name].label} and {setting.label} would be the same run folder "
                              f"{name}; give densities that differ within 6 significant digits")
        folders[name] = setting
    checked = set()
    for setting in grid.settings:
        cell = Cell(setting, grid.seeds[0])
        try:
            cfg = grid.config(cell)
            check_trainable(cfg)  # a run the grid holds must be able to train: said before any run starts
            if (setting.density, cfg.road.length_m) not in checked:
                check_fits(cfg)
                checked.add((setting.density, cfg.road.length_m))
        except ConfigError as exc:
            raise ConfigError(f"{where}: {setting.label}: {exc}") from None
    # the overrides as the config normalises them (tuples → lists), so saved and loaded grids compare equal
    normal = config_to_dict(base)
    variants = {name: _subset(config_to_dict(merge_config(LaneFreeConfig(), keys)), keys)
                for name, keys in grid.variants.items()}
    return Grid(grid.name, grid.settings, grid.seeds, grid.episodes, _subset(normal, grid.overrides), variants,
                grid.compare)


def _subset(full: Mapping[str, Any], keys: Mapping[str, Any]) -> dict[str, Any]:
    """The entries of ``full`` at the keys of ``keys`` (nested)."""
    out: dict[str, Any] = {}
    for key, value in keys.items():
        if not isinstance(value, Mapping):
            out[key] = full[key]
        elif value:
            out[key] = _subset(full[key], value)
    return out

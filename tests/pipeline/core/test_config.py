"""Tests of pipeline.core.config: typed configs from YAML profiles, config files and CLI overrides."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

import pytest
import yaml

from pipeline.core.config import (
    PROFILES_ENV,
    BaseStageConfig,
    apply_dict,
    available_profiles,
    config_hash,
    describe_fields,
    dump_yaml,
    from_dict,
    hash_excluded_fields,
    load_config,
    parse_overrides,
    profiles_dir,
    to_dict,
    validate_tree,
)
from pipeline.core.errors import ConfigError, InputMissingError

VALIDATED: list[str] = []


@dataclass
class CameraConfig:
    width_px: int = field(default=64, metadata={"help": "image width"})
    height_px: int = field(default=48, metadata={"help": "image height"})
    fov_deg: float = 90.0

    def validate(self) -> None:
        VALIDATED.append("camera")
        if self.width_px <= 0:
            raise ConfigError(f"config key 'sim.camera.width_px': expected > 0, got {self.width_px}")


@dataclass
class SimConfig:
    dt_s: float = 0.1
    camera: CameraConfig = field(default_factory=CameraConfig)
    render: Literal["rgb", "depth", "rgbd"] = "rgbd"
    scenes: list[str] = field(default_factory=lambda: ["lobby"])
    density_per_m2: tuple[float, ...] = (0.1, 0.2)
    arena_m: tuple[float, float] = (10.0, 8.0)
    max_peds: int | None = None
    weights: dict[str, float] = field(default_factory=dict)
    out_path: Path = Path("x/y")

    def validate(self) -> None:
        VALIDATED.append("sim")


@dataclass
class ToyConfig(BaseStageConfig):
    episodes: int = field(default=4, metadata={"help": "number of episodes"})
    max_episode_s: float = 30.0
    record: bool = True
    sim: SimConfig = field(default_factory=SimConfig)

    def validate(self) -> None:
        super().validate()
        VALIDATED.append("toy")


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


@pytest.fixture
def profiles(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "profiles"
    write(
        d / "default.yaml",
        "common:\n  seed: 3\n  not_a_toy_key: 1\n  sim: {dt_s: 0.05, unknown_nested: 2}\n"
        "toy:\n  episodes: 10\n  sim:\n    camera: {width_px: 32}\n"
        "other_stage:\n  whatever: 1\n",
    )
    write(d / "smoke.yaml", "# smoke\ncommon: {}\n")
    write(d / "broken.yaml", "toy:\n  episodes: [1, 2\n")
    write(d / "typo.yaml", "toy:\n  sim:\n    camera:\n      widht_px: 3\n")
    monkeypatch.setenv(PROFILES_ENV, str(d))
    VALIDATED.clear()
    return d


def test_profiles_dir_env_and_listing(profiles: Path) -> None:
    assert profiles_dir() == profiles
    assert available_profiles() == ["broken", "default", "smoke", "typo"]
    assert profiles_dir(Path("/elsewhere")) == Path("/elsewhere")


def test_repo_profiles_exist(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(PROFILES_ENV, raising=False)
    assert {"smoke", "default", "paper"} <= set(available_profiles())


def test_defaults_and_nested_partial_dict_keeps_defaults() -> None:
    cfg = from_dict(ToyConfig, {"sim": {"camera": {"width_px": 5}}}, "t.yaml")
    assert cfg.sim.camera.width_px == 5
    assert cfg.sim.camera.height_px == 48
    assert cfg.sim.dt_s == 0.1
    assert cfg.episodes == 4
    assert cfg.data_dir == Path("data")


def test_apply_dict_keeps_previous_layer() -> None:
    cfg = from_dict(ToyConfig, {"sim": {"camera": {"width_px": 5}}}, "a.yaml")
    cfg2 = apply_dict(cfg, {"sim": {"camera": {"height_px": 7}}}, "b.yaml")
    assert (cfg2.sim.camera.width_px, cfg2.sim.camera.height_px) == (5, 7)
    assert cfg.sim.camera.height_px == 48  # not modified


def test_unknown_key_names_key_source_and_valid_keys() -> None:
    with pytest.raises(ConfigError) as e:
        from_dict(ToyConfig, {"sim": {"camera": {"widht_px": 5}}}, "my.yaml")
    msg = str(e.value)
    assert "'sim.camera.widht_px'" in msg and "my.yaml" in msg
    assert "fov_deg, height_px, width_px" in msg


def test_wrong_type_names_key_expected_and_actual() -> None:
    with pytest.raises(
        ConfigError, match=r"config key 'episodes' in my.yaml: expected int, got 'abc' \(str\)"
    ):
        from_dict(ToyConfig, {"episodes": "abc"}, "my.yaml")
    with pytest.raises(ConfigError, match=r"'record'.*expected bool, got 'yes please' \(str\)"):
        from_dict(ToyConfig, {"record": "yes please"}, "my.yaml")
    with pytest.raises(ConfigError, match=r"'episodes'.*expected int, got True \(bool\)"):
        from_dict(ToyConfig, {"episodes": True}, "my.yaml")
    with pytest.raises(ConfigError, match=r"'sim.scenes\[1\]'.*expected str, got 3 \(int\)"):
        from_dict(ToyConfig, {"sim": {"scenes": ["a", 3]}}, "my.yaml")
    with pytest.raises(ConfigError, match=r"'sim.arena_m'.*tuple\[float, float\].*2 items"):
        from_dict(ToyConfig, {"sim": {"arena_m": [1, 2, 3]}}, "my.yaml")
    with pytest.raises(ConfigError, match=r"'sim' in my.yaml: expected SimConfig, got 3 \(int\)"):
        from_dict(ToyConfig, {"sim": 3}, "my.yaml")


def test_bad_literal_lists_allowed_values() -> None:
    with pytest.raises(ConfigError) as e:
        from_dict(ToyConfig, {"sim": {"render": "ir"}}, "my.yaml")
    assert (
        str(e.value)
        == "config key 'sim.render' in my.yaml: expected one of 'rgb', 'depth', 'rgbd', got 'ir' (str)"
    )


def test_supported_types_from_yaml() -> None:
    cfg = from_dict(
        ToyConfig,
        {
            "max_episode_s": 5,  # int accepted for float
            "data_dir": "/tmp/d",
            "sim": {
                "dt_s": "1e-3",  # YAML reads 1e-3 as a string
                "density_per_m2": [0.5],
                "arena_m": [3, 4],
                "max_peds": 12,
                "weights": {"a": 1, "b": 0.5},
                "render": "depth",
            },
        },
        "t.yaml",
    )
    assert cfg.max_episode_s == 5.0 and isinstance(cfg.max_episode_s, float)
    assert cfg.data_dir == Path("/tmp/d")
    assert cfg.sim.dt_s == pytest.approx(1e-3)
    assert cfg.sim.density_per_m2 == (0.5,)
    assert cfg.sim.arena_m == (3.0, 4.0)
    assert cfg.sim.max_peds == 12
    assert cfg.sim.weights == {"a": 1.0, "b": 0.5}
    assert cfg.sim.render == "depth"
    assert from_dict(ToyConfig, {"sim": {"max_peds": None}}, "t").sim.max_peds is None


def test_dotted_cli_keys_into_a_dict_field_merge_and_whole_text_replaces() -> None:
    base = from_dict(ToyConfig, {"sim": {"weights": {"a": 1, "b": 0.5}}}, "t.yaml")
    merged = apply_dict(base, parse_overrides({"sim.weights.b": "2"}), "command line")
    assert merged.sim.weights == {"a": 1.0, "b": 2.0}
    added = apply_dict(base, parse_overrides({"sim.weights.c": "3"}), "command line")
    assert added.sim.weights == {"a": 1.0, "b": 0.5, "c": 3.0}
    whole = apply_dict(base, parse_overrides({"sim.weights": "{c: 3}"}), "command line")
    assert whole.sim.weights == {"c": 3.0}
    layered = apply_dict(base, {"sim": {"weights": {"c": 3}}}, "other.yaml")  # a YAML layer replaces
    assert layered.sim.weights == {"c": 3.0}


def test_cli_overrides_parse_strings_for_the_field_type() -> None:
    base = from_dict(ToyConfig, {}, "defaults")
    cfg = apply_dict(
        base,
        parse_overrides(
            {
                "--max-episode-s": "2.5",
                "record": "no",
                "overwrite": "1",
                "sim.scenes": "a,b,c",
                "sim.density_per_m2": "[0.3, 0.4]",
                "sim.arena_m": "5,6",
                "sim.max_peds": "none",
                "sim.weights": "{x: 2}",
                "sim.render": "rgb",
                "profile": "123",  # str fields take the text verbatim
            }
        ),
        "command line",
    )
    assert cfg.max_episode_s == 2.5
    assert cfg.record is False and cfg.overwrite is True
    assert cfg.sim.scenes == ["a", "b", "c"]
    assert cfg.sim.density_per_m2 == (0.3, 0.4)
    assert cfg.sim.arena_m == (5.0, 6.0)
    assert cfg.sim.max_peds is None
    assert cfg.sim.weights == {"x": 2.0}
    assert cfg.profile == "123"
    with pytest.raises(ConfigError, match=r"'episodes' in command line: expected int, got 'abc' \(str\)"):
        apply_dict(base, parse_overrides({"episodes": "abc"}), "command line")
    with pytest.raises(ConfigError, match=r"'record' in command line: expected bool, got 'maybe'"):
        apply_dict(base, parse_overrides({"record": "maybe"}), "command line")
    with pytest.raises(ConfigError, match="conflicting"):
        parse_overrides({"sim": "{}", "sim.dt_s": "1"})


def test_load_config_precedence_profile_file_cli(profiles: Path, tmp_path: Path) -> None:
    cfg = load_config(ToyConfig, "toy")
    assert cfg.profile == "default"
    assert cfg.seed == 3  # common
    assert cfg.sim.dt_s == 0.05  # common, nested, unknown keys of common ignored
    assert cfg.episodes == 10  # stage section
    assert cfg.sim.camera.width_px == 32

    cfg_file = write(tmp_path / "extra.yaml", "toy:\n  episodes: 20\n  max_episode_s: 7\nother: {x: 1}\n")
    cfg = load_config(ToyConfig, "toy", config_file=cfg_file)
    assert (cfg.episodes, cfg.max_episode_s, cfg.sim.camera.width_px) == (20, 7.0, 32)

    cfg = load_config(ToyConfig, "toy", overrides={"episodes": "30"}, config_file=cfg_file)
    assert (cfg.episodes, cfg.max_episode_s) == (30, 7.0)

    cfg = load_config(ToyConfig, "toy", profile="smoke")
    assert (cfg.profile, cfg.episodes, cfg.seed) == ("smoke", 4, 0)


def test_unknown_profile_lists_available(profiles: Path) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(ToyConfig, "toy", profile="papr")
    msg = str(e.value)
    assert "unknown profile 'papr'" in msg and "broken, default, smoke, typo" in msg


def test_malformed_yaml_names_file(profiles: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"malformed YAML in profile .*broken\.yaml"):
        load_config(ToyConfig, "toy", profile="broken")
    bad = write(tmp_path / "bad.yaml", "toy: [\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml"):
        load_config(ToyConfig, "toy", config_file=bad)
    notmap = write(tmp_path / "list.yaml", "- 1\n- 2\n")
    with pytest.raises(ConfigError, match=r"list\.yaml: expected a mapping"):
        load_config(ToyConfig, "toy", config_file=notmap)


def test_unknown_key_in_profile_names_profile_file(profiles: Path) -> None:
    with pytest.raises(ConfigError, match=r"unknown config key 'sim.camera.widht_px' in .*typo\.yaml"):
        load_config(ToyConfig, "toy", profile="typo")


def test_missing_config_file(profiles: Path, tmp_path: Path) -> None:
    with pytest.raises(InputMissingError, match=r"missing config file: .*nope\.yaml"):
        load_config(ToyConfig, "toy", config_file=tmp_path / "nope.yaml")


def test_validate_runs_on_nested_dataclasses_children_first(profiles: Path) -> None:
    load_config(ToyConfig, "toy")
    assert VALIDATED == ["camera", "sim", "toy"]
    with pytest.raises(ConfigError, match=r"sim.camera.width_px.*got -1"):
        load_config(ToyConfig, "toy", overrides={"sim.camera.width_px": "-1"})


def test_base_validate(profiles: Path) -> None:
    with pytest.raises(ConfigError, match="overwrite.*resume"):
        load_config(ToyConfig, "toy", overrides={"overwrite": "true", "resume": "true"})
    with pytest.raises(ConfigError, match=r"'seed'.*got -2"):
        load_config(ToyConfig, "toy", overrides={"seed": "-2"})


def test_validate_tree_wraps_value_error() -> None:
    @dataclass
    class Inner:
        def validate(self) -> None:
            raise ValueError("bad inner")

    @dataclass
    class Outer:
        items: list[Inner] = field(default_factory=lambda: [Inner()])

    with pytest.raises(ConfigError, match=r"'items\[0\]': bad inner"):
        validate_tree(Outer())


def test_to_dict_hash_and_yaml_round_trip(tmp_path: Path) -> None:
    cfg = from_dict(ToyConfig, {"sim": {"arena_m": [1, 2]}}, "t")
    data = to_dict(cfg)
    json.dumps(data)  # JSON-able
    assert data["data_dir"] == "data" and data["sim"]["arena_m"] == [1.0, 2.0]

    h = config_hash(cfg)
    assert len(h) == 64
    assert config_hash(apply_dict(cfg, {"overwrite": True}, "t")) == h
    assert config_hash(apply_dict(cfg, {"resume": True}, "t")) == h
    assert config_hash(apply_dict(cfg, {"episodes": 5}, "t")) != h

    path = dump_yaml(cfg, tmp_path / "sub" / "config.yaml")
    loaded = yaml.safe_load(path.read_text())
    assert from_dict(ToyConfig, loaded, str(path)) == cfg
    assert [p.name for p in path.parent.iterdir()] == ["config.yaml"]  # no temp file left


@dataclass
class PlacedConfig(ToyConfig):
    PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("workers",)
    workers: int = 2


def test_the_fields_a_stage_names_as_placement_are_out_of_its_hash() -> None:
    """``workers`` says how parallel a run is, not what it makes: another count keeps the hash (a run resumed on a
    bigger machine keeps its output); every other field still changes it; a name that is not a field is a bug."""
    cfg = PlacedConfig()
    assert "workers" in hash_excluded_fields(cfg) and "workers" not in hash_excluded_fields(ToyConfig())
    assert config_hash(apply_dict(cfg, {"workers": 7}, "t")) == config_hash(cfg)
    assert config_hash(apply_dict(cfg, {"episodes": 5}, "t")) != config_hash(cfg)
    assert "workers" in to_dict(cfg) and "PLACEMENT_FIELDS" not in to_dict(cfg)  # still recorded, not a field

    @dataclass
    class Misnamed(ToyConfig):
        PLACEMENT_FIELDS: ClassVar[tuple[str, ...]] = ("wokers",)

    with pytest.raises(TypeError, match=r"Misnamed\.PLACEMENT_FIELDS .*\['wokers'\]"):
        config_hash(Misnamed())


def test_each_stage_leaves_out_only_what_does_not_change_its_output() -> None:
    """Episode-seeded stages drop ``workers``; the torch stages drop ``threads``; ``train`` drops both (its episodes
    are seeded one by one and gathered in job order: tests/rl/baselines/sarl_om/test_training.py); ``export`` keeps
    ``workers`` (the shard count of the dataset it writes)."""
    from evaluation.stage import EvalConfig
    from pretrain.intention import IntentionConfig
    from pretrain.stage import PretrainConfig
    from recorder.export_stage import ExportConfig
    from recorder.record import RecordConfig
    from rl.stage import TrainConfig
    from sim.rollout import RolloutConfig

    base = hash_excluded_fields(BaseStageConfig())
    own = {c.__name__: hash_excluded_fields(c()) - base for c in (RecordConfig, RolloutConfig, EvalConfig,
                                                                 ExportConfig, IntentionConfig, PretrainConfig,
                                                                 TrainConfig)}
    assert own == {"RecordConfig": {"workers"}, "RolloutConfig": {"workers"}, "EvalConfig": {"workers"},
                   "ExportConfig": set(), "IntentionConfig": {"threads"}, "PretrainConfig": {"threads"},
                   "TrainConfig": {"threads", "workers"}}
    assert config_hash(TrainConfig(workers=1, threads=1)) == config_hash(TrainConfig(workers=8, threads=2))
    assert config_hash(ExportConfig(workers=1)) != config_hash(ExportConfig(workers=2))


def test_describe_fields() -> None:
    rows = {r[0]: r for r in describe_fields(ToyConfig)}
    assert rows["episodes"] == ("episodes", "int", "4", "number of episodes")
    assert rows["sim.camera.width_px"][1:] == ("int", "64", "image width")
    assert rows["sim.render"][1] == "{'rgb', 'depth', 'rgbd'}"
    assert rows["sim.max_peds"][1] == "int | None"
    assert rows["data_dir"][2] == "data"
    assert "sim" not in rows and "sim.camera" not in rows
    assert all(help_ for key, _, _, help_ in describe_fields(BaseStageConfig))

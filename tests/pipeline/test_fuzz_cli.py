"""Seeded fuzz of bad input through the CLI entry point (:func:`pipeline.cli.main`).

Generated bad scene files, scenario files, command-line values, config files and damaged artifacts (MCAPs, a
LeRobot dataset, manifests); each one must exit 2 with exactly one ``error:`` line on stderr and no traceback,
and leave the data directory as it was. Candidates are drawn from a fixed seed; a generated scene or scenario
that happens to be valid (the parser accepts it) is dropped before it reaches the CLI, so every case is bad input.
"""

from __future__ import annotations

import copy
import math
import random
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from pipeline import cli
from pipeline.core.config import describe_fields
from sim.scenario import SCENARIOS_DIR, parse_scenario
from sim.scene import SCENES_DIR, parse_scene

SEED = 2024
TINY = ["--densities", "0.05", "--episodes", "1", "--sim.max-episode-s", "1.0", "--sim.camera.width-px", "64",
        "--sim.camera.height-px", "48", "--workers", "1"]
BAD_NUMBERS = [math.nan, math.inf, -math.inf, "wide", [1.0], {"x": 1}, True, None]
SCENES = ["hallway", "office_lobby", "warehouse", "corner", "office_floor"]
SCENARIOS = ["head_on", "blind_corner", "doorway"]


def snapshot(root: Path) -> dict[str, int]:
    return {p.relative_to(root).as_posix(): p.stat().st_size for p in root.rglob("*")} if root.exists() else {}


def run_bad(capsys, argv: list[str], data: Path, what: str) -> None:
    """``argv`` must exit 2 with one ``error:`` line and leave ``data`` untouched."""
    before = snapshot(data)
    rc = cli.main(argv)
    _, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error: ")]
    assert rc == 2 and len(errors) == 1, f"{what}: rc {rc}, stderr:\n{err}"
    assert "Traceback" not in err, f"{what}:\n{err}"
    assert snapshot(data) == before, f"{what}: the data directory changed"


def leaves(node: Any, path: tuple = ()) -> list[tuple]:
    """Paths of every number in a nested YAML structure."""
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in leaves(v, (*path, k))]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in leaves(v, (*path, i))]
    return [path] if isinstance(node, int | float) and not isinstance(node, bool) else []


def mappings(node: Any, path: tuple = ()) -> list[tuple]:
    """Paths of every mapping in a nested YAML structure."""
    out = [path] if isinstance(node, dict) else []
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
    return out + [p for k, v in children for p in mappings(v, (*path, k))]


def setpath(data: Any, path: tuple, value: Any) -> None:
    for k in path[:-1]:
        data = data[k]
    data[path[-1]] = value


def getpath(data: Any, path: tuple) -> Any:
    for k in path:
        data = data[k]
    return data


def mutate(rng: random.Random, data: dict, required: list[str]) -> tuple[Any, str]:
    """One random damage of a parsed YAML file: a bad number, a missing required key, an unknown key, a wrong
    top-level type; returns (new data or raw text, description)."""
    data = copy.deepcopy(data)
    kind = rng.choice(["number", "number", "number", "missing", "unknown", "text"])
    if kind == "number":
        path = rng.choice(leaves(data))
        value = rng.choice(BAD_NUMBERS)
        setpath(data, path, value)
        return data, f"{'.'.join(map(str, path))}={value!r}"
    if kind == "missing":
        key = rng.choice(required)
        del data[key]
        return data, f"without {key}"
    if kind == "unknown":
        path = rng.choice(mappings(data))
        getpath(data, path)[f"bogus_{rng.randrange(100)}"] = 1
        return data, f"unknown key under {'.'.join(map(str, path)) or 'top level'}"
    text = yaml.safe_dump(data)
    cut = rng.randrange(1, len(text) - 1)
    return text[:cut] + rng.choice(["\x00\x01", ": [", "\t- {", "]]", ""]), f"text cut at {cut}"


def bad_files(rng: random.Random, folder: Path, names: list[str], parse, required: list[str], n: int,
              tmp: Path) -> list[tuple[Path, str]]:
    """``n`` damaged copies of shipped files that the parser rejects (any exception counts: a non-ConfigError
    is exactly what the CLI run must turn into one error line or expose as a bug)."""
    out: list[tuple[Path, str]] = []
    while len(out) < n:
        name = rng.choice(names)
        data, what = mutate(rng, yaml.safe_load((folder / f"{name}.yaml").read_text()), required)
        path = tmp / f"case{len(out)}" / f"{name}.yaml"  # the stem stays the name (else that is the error)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
        try:
            parse(yaml.safe_load(path.read_text()), str(path), name)
        except Exception:
            out.append((path, f"{name}: {what}"))
    return out


@pytest.fixture(scope="module")
def rng() -> random.Random:
    return random.Random(SEED)


def test_fuzz_bad_scene_files(tmp_path, capsys, rng):
    data = tmp_path / "data"
    cases = bad_files(rng, SCENES_DIR, SCENES, parse_scene, ["name", "split", "bounds"], 24, tmp_path / "scenes")
    for path, what in cases:
        run_bad(capsys, ["record", "--data-dir", str(data), "--scenes", str(path), *TINY], data, what)
    assert not data.exists()


def test_fuzz_bad_scenario_files(tmp_path, capsys, rng):
    data = tmp_path / "data"
    cases = bad_files(rng, SCENARIOS_DIR, SCENARIOS, parse_scenario, ["name", "start", "goal"], 12,
                      tmp_path / "scenarios")
    for path, what in cases:
        run_bad(capsys, ["rollout", "--data-dir", str(data), "--sim.scenario", str(path)], data, what)
    assert not data.exists()


def _numeric_keys(stage) -> list[tuple[str, str]]:
    return [(key, tname.split(" ")[0]) for key, tname, _, _ in describe_fields(stage.config_cls)
            if tname in ("float", "int", "float | None", "int | None")]


@pytest.mark.slow
def test_fuzz_bad_command_line_values_and_config_files(tmp_path, capsys, rng):
    from pipeline.cli import resolve_verb

    data = tmp_path / "data"
    verbs = ["record", "export", "pretrain", "train", "eval", "rollout"]
    cases: list[tuple[list[str], str]] = []
    for _ in range(24):
        verb = rng.choice(verbs)
        key, tname = rng.choice(_numeric_keys(resolve_verb(verb)))
        value = rng.choice(["nan", "inf", "-inf", "abc", "1e999", "[1, 2", "{}"] + (["1.5"] if tname == "int" else []))
        cases.append(([verb, "--data-dir", str(data), f"--{key}", value], f"{verb} --{key} {value}"))
    config = tmp_path / "cfg.yaml"
    for k, text in enumerate(["[1, 2]", "common: 3", "record: {episodes: nan}", "record: {sim: {dt_s: .inf}}",
                              "record: {nope: 1}", "common: {seed: -1}", ": :", "record: {scenes: [nowhere]}"]):
        path = config.with_name(f"cfg{k}.yaml")
        path.write_text(text)
        cases.append((["record", "--data-dir", str(data), "--config", str(path)], f"config file {text!r}"))
    cases += [(["record", "--data-dir", str(data), "--profile", "nope"], "unknown profile"),
              (["record", "--data-dir", str(data), "--no-such-key", "1"], "unknown key"),
              (["record", "--data-dir", str(data), "--overwrite", "--resume"], "overwrite and resume"),
              (["nope"], "unknown verb")]
    for argv, what in cases:
        run_bad(capsys, argv, data, what)
    assert len(cases) >= 36 and not data.exists()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A finished tiny recording (2 episodes) and its export; returns DATA_DIR (tests copy it before damaging)."""
    data = tmp_path_factory.mktemp("fuzz") / "data"
    assert cli.main(["record", "--data-dir", str(data), "--scenes", "hallway", *TINY[:2], "--episodes", "2",
                     *TINY[4:]]) == 0
    assert cli.main(["export", "--data-dir", str(data), "--repo-id", "test/tiny"]) == 0
    return data


def _damage(rng: random.Random, path: Path) -> str:
    blob = bytearray(path.read_bytes())
    kind = rng.choice(["truncate", "flip", "zero"])
    lo, hi = len(blob) // 10, len(blob) * 9 // 10
    if kind == "truncate":
        cut = rng.randrange(lo, hi)
        path.write_bytes(bytes(blob[:cut]))
        return f"truncated to {cut} of {len(blob)} bytes"
    at = rng.randrange(lo, hi - 64)
    for i in range(at, at + 64):
        blob[i] = (blob[i] ^ 0xA5) if kind == "flip" else 0
    path.write_bytes(bytes(blob))
    return f"64 bytes {kind}ped at {at}"


def test_fuzz_damaged_artifacts(tmp_path, capsys, rng, recorded):
    cases = 0
    for k in range(16):
        data = tmp_path / f"d{k}"
        shutil.copytree(recorded, data)
        raw = data / "raw" / "expert"
        target = rng.choice(["mcap", "mcap", "manifest", "seeds", "rows"])
        if target == "mcap":
            mcap = rng.choice(sorted(raw.glob("*.mcap")))
            what = f"{mcap.name} {_damage(rng, mcap)}"
        elif target == "manifest":
            (raw / "manifest.json").write_text(rng.choice(["{", "[]", '{"stage": 3}', "\x00"]))
            what = "manifest.json damaged"
        elif target == "seeds":
            (raw / "seeds.json").write_text(rng.choice(["{", '{"episodes": 3}', "null"]))
            what = "seeds.json damaged"
        else:
            (raw / "episodes.jsonl").write_text(rng.choice(["{\n", '{"file": 1}\n', "[]\n"]))
            what = "episodes.jsonl damaged"
        shutil.rmtree(data / "datasets")
        run_bad(capsys, ["export", "--data-dir", str(data), "--repo-id", "test/tiny"], data, what)
        cases += 1
    assert cases == 16

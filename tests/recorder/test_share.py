"""Sharing a dataset: the dataset card, the push-ready copy (no local paths, no command line), the CLI, --push."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from pipeline.core.errors import ConfigError, ICrowdNavError
from pipeline.core.manifest import Manifest
from recorder.share import (
    CARD,
    ICROWDNAV_EPISODES,
    ICROWDNAV_META,
    INFO,
    NOT_RECORDED,
    PAPER_TITLE,
    PROVENANCE,
    PROVENANCE_KEYS,
    TAGS,
    LocalPathError,
    dataset_card,
    main,
    stage_for_sharing,
)

COMMAND = ["icrowdnav", "export", "--profile", "tiny", "--run-name", "tiny", "--overwrite"]


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data, indent=2))


def _edit_rows(path: Path, edit) -> None:
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    for r in rows:
        edit(r)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))


@pytest.fixture
def shareable(tmp_path: Path, tiny_dataset) -> Path:
    """The tiny dataset as the export stage leaves it: ``DATA_DIR/datasets/icrowdnav/tiny`` with a manifest (an
    absolute data dir in its params) and a config.yaml."""
    data_dir = tmp_path / "data"
    root = data_dir / "datasets" / "icrowdnav" / "tiny"
    shutil.copytree(tiny_dataset.root, root)
    counts = {k: v for k, v in tiny_dataset.counts.items() if isinstance(v, int | float | str)}
    Manifest(stage="export", params={"data_dir": str(data_dir), "repo_id": tiny_dataset.repo_id, "run_name": "tiny"},
             config_hash="c" * 64, seed=0, counts=counts, created_utc="2026-01-02T03:04:05Z", git_commit="a" * 40,
             git_dirty=True, versions={"lerobot": "0.4.4"}, duration_s=1.0, command=list(COMMAND),
             code_hash="b" * 64).write(root / "manifest.json")
    (root / "config.yaml").write_text(f"{{data_dir: {data_dir}, repo_id: {tiny_dataset.repo_id}}}\n")
    return root


# ----------------------------------------------------------------------------------------------------------- card
def test_card_has_front_matter_features_convention_and_citation(tiny_dataset):
    from huggingface_hub import DatasetCard

    card = dataset_card(tiny_dataset.root)
    data = DatasetCard(card).data.to_dict()
    assert data["license"] == "apache-2.0" and data["task_categories"] == ["robotics"]
    assert data["tags"] == TAGS
    assert data["configs"] == [{"config_name": "default", "data_files": "data/*/*.parquet"}]
    info = json.loads((tiny_dataset.root / INFO).read_text())
    rows = {line.split(" | ")[0]: line for line in card.splitlines() if line.startswith("| `")}
    assert sorted(rows) == sorted(f"| `{name}`" for name in info["features"])
    assert "m/s" in rows["| `observation.state`"] and "(5,)" in rows["| `observation.state`"]
    assert "## Action convention" in card and "## Cameras" in card and "### `left`" in card
    assert "**Scenes:** hallway (2 episodes)" in card and "0.2 ped/m²" in card and "**Driver:** expert" in card
    assert f"**frames:** {tiny_dataset.counts['frames']}" in card
    assert "@article{" in card and PAPER_TITLE in card and "Bao, Han" in card and "Wang, Jiankun" in card
    assert "IEEE Robotics and Automation Letters" in card and "2026" in card
    assert f'LeRobotDataset("{tiny_dataset.repo_id}"' in card and 'video_backend="pyav"' in card
    assert "torchcodec" in card and "Apache-2.0" in card
    assert f"code version {NOT_RECORDED}" in card  # export_run writes no manifest
    assert str(tiny_dataset.root) not in card


def test_card_reads_the_format_2_feature_info(dataset_copy):
    convention = "action[t] = the command [v m/s, ω rad/s] chosen from observation t"
    cam = {"width": 64, "height": 48, "K": [[51.5, 0, 32], [0, 51.5, 24], [0, 0, 1]],
           "T_base_cam": [[0, 0, 1, 0.1], [-1, 0, 0, 0.03], [0, -1, 0, 0.8], [0, 0, 0, 1]], "hfov_deg": 64.0}

    def edit(info):
        f = info["features"]
        f["action"]["info"] = {"description": "the command [v m/s, ω rad/s]", "convention": convention,
                               "icrowdnav_format": 2}
        f["observation.depth.left"].update(dtype="uint16", info={"description": "z-depth, uint16 mm", "camera": cam})
        f["observation.images.left"]["info"]["camera"] = cam
        for key in ("observation.images.right", "observation.depth.right"):
            f[key].get("info", {}).pop("camera", None)

    _edit_json(dataset_copy / INFO, edit)
    (dataset_copy / ICROWDNAV_META).unlink()  # the camera model must come from info.json
    card = dataset_card(dataset_copy)
    section = card.split("## Action convention")[1].split("##")[0]
    assert convention in section
    assert "**iCrowdNav dataset format:** 2" in card
    assert "| `observation.depth.left` | uint16 | (48, 64) | height, width | z-depth, uint16 mm |" in card
    left = card.split("### `left`")[1].split("### `right`")[0]
    assert "51.5" in left and "T_base_cam" in left and "`hfov_deg`: 64.0" in left and "meta/info.json" in left
    right = card.split("### `right`")[1].split("## Loading")[0]
    assert f"Intrinsics and extrinsics: {NOT_RECORDED}" in right


def test_card_says_not_recorded_for_missing_keys(dataset_copy):
    def edit(info):
        for k in ("fps", "robot_type", "total_frames"):
            info.pop(k)
        for ft in info["features"].values():
            ft.pop("info", None)
            ft.pop("shape", None)

    _edit_json(dataset_copy / INFO, edit)
    (dataset_copy / ICROWDNAV_META).unlink()
    (dataset_copy / ICROWDNAV_EPISODES).unlink()
    card = dataset_card(dataset_copy)
    assert f"**Scenes:** {NOT_RECORDED}" in card and f"**fps:** {NOT_RECORDED}" in card
    assert f"Not recorded in `meta/info.json` (iCrowdNav dataset format {NOT_RECORDED})" in card
    assert f"| `observation.state` | float32 | {NOT_RECORDED} |" in card
    assert f"Intrinsics and extrinsics: {NOT_RECORDED}" in card


# ------------------------------------------------------------------------------------------------- staged copy
def test_staged_copy_loads_with_stock_lerobot_and_holds_no_local_state(shareable, tmp_path, tiny_dataset):
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    # as older exports recorded them: each episode's MCAP by its absolute path (here outside the data dir)
    elsewhere = tmp_path / "elsewhere" / "raw"
    _edit_json(shareable / ICROWDNAV_META,
               lambda m: m.update(sources=[str(elsewhere / Path(s).name) for s in m["sources"]]))
    _edit_rows(shareable / ICROWDNAV_EPISODES, lambda r: r.update(source=str(elsewhere / Path(r["source"]).name)))
    names = [Path(s).name for s in json.loads((shareable / ICROWDNAV_META).read_text())["sources"]]
    before = _digest(shareable)
    out = tmp_path / "share" / "tiny"
    counts = stage_for_sharing(shareable, out)
    assert _digest(shareable) == before  # the dataset, manifest included, is untouched

    files = _digest(out)
    shared = {k for k in before if k.split("/")[0] in ("meta", "data", "videos")}
    assert set(files) == shared | {CARD, PROVENANCE}
    assert "manifest.json" not in files and "config.yaml" not in files
    assert counts["files"] == len(files) and counts["bytes"] == sum(p.stat().st_size for p in out.rglob("*")
                                                                     if p.is_file())
    parquet = "data/chunk-000/file-000.parquet"
    assert counts["linked"] > 0 and (out / parquet).stat().st_ino == (shareable / parquet).stat().st_ino
    assert not list(out.parent.glob(".tiny.*"))

    prov = json.loads((out / PROVENANCE).read_text())
    manifest = Manifest.read(shareable / "manifest.json")
    assert prov == {k: getattr(manifest, k) for k in PROVENANCE_KEYS}
    assert "command" not in prov and "git_dirty" in prov
    assert "a" * 40 in (out / CARD).read_text() and "uncommitted changes" in (out / CARD).read_text()

    # the recording's absolute MCAP paths (outside the data dir) are reduced to file names
    assert json.loads((out / ICROWDNAV_META).read_text())["sources"] == names == ["ep_000.mcap", "ep_001.mcap"]
    assert set(counts["rewritten"]) == {ICROWDNAV_META, ICROWDNAV_EPISODES}
    for p in out.rglob("*"):
        if p.suffix in (".json", ".jsonl", ".md", ".yaml"):
            text = p.read_text()
            for bad in (str(tmp_path), str(tiny_dataset.root.parent), " ".join(COMMAND)):
                assert bad not in text, (p, bad)

    ours = LeRobotDataset(tiny_dataset.repo_id, root=shareable, video_backend="pyav")
    theirs = LeRobotDataset(tiny_dataset.repo_id, root=out, video_backend="pyav")
    assert theirs.num_episodes == ours.num_episodes == tiny_dataset.counts["episodes"]
    assert len(theirs) == len(ours) == tiny_dataset.counts["frames"]
    for i in range(len(ours)):
        a, b = ours[i], theirs[i]
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k], (i, k)
    assert _digest(out) == files  # loading wrote nothing into the copy


def test_absolute_paths_under_the_data_dir_become_relative(shareable, tmp_path):
    data_dir = tmp_path / "data"
    _edit_json(shareable / ICROWDNAV_META,
               lambda m: m.update(sources=[str(data_dir / "raw" / "tiny" / Path(s).name) for s in m["sources"]]))

    def row(r):
        r["source"] = str(data_dir / "raw" / "tiny" / Path(r["source"]).name)
        r["driver"] = r["meta"]["driver"] = str(data_dir / "checkpoints" / "policy" / "teacher")

    _edit_rows(shareable / ICROWDNAV_EPISODES, row)
    before = _digest(shareable)
    out = tmp_path / "share" / "tiny"
    stage_for_sharing(shareable, out)
    assert json.loads((out / ICROWDNAV_META).read_text())["sources"] == ["raw/tiny/ep_000.mcap",
                                                                        "raw/tiny/ep_001.mcap"]
    assert json.loads((shareable / ICROWDNAV_META).read_text())["sources"][0] == str(data_dir / "raw/tiny/ep_000.mcap")
    rows = [json.loads(line) for line in (out / ICROWDNAV_EPISODES).read_text().splitlines()]
    assert [r["source"] for r in rows] == ["raw/tiny/ep_000.mcap", "raw/tiny/ep_001.mcap"]
    assert {r["driver"] for r in rows} == {r["meta"]["driver"] for r in rows} == {"checkpoints/policy/teacher"}
    assert "**Driver:** checkpoints/policy/teacher (2 episodes)" in (out / CARD).read_text()
    assert _digest(shareable) == before


def _inject_root(root: Path, tmp_path: Path) -> tuple[str, str]:
    _edit_json(root / ICROWDNAV_META, lambda m: m.update(note=f"exported from {root.resolve()}"))
    return ICROWDNAV_META, str(root.resolve())


def _inject_cwd(root: Path, tmp_path: Path) -> tuple[str, str]:
    _edit_json(root / INFO, lambda i: i["features"]["action"].setdefault("info", {}).update(
        description=f"see {Path.cwd()}/notes.txt"))
    return INFO, str(Path.cwd())


def _inject_home(root: Path, tmp_path: Path) -> tuple[str, str]:
    _edit_rows(root / ICROWDNAV_EPISODES, lambda r: r.update(note="/home/someone/notes.txt"))
    return ICROWDNAV_EPISODES, "/home/someone"


def _inject_command(root: Path, tmp_path: Path) -> tuple[str, str]:
    _edit_json(root / ICROWDNAV_META, lambda m: m.update(made_by=" ".join(COMMAND)))
    return ICROWDNAV_META, " ".join(COMMAND)


def _inject_other_path(root: Path, tmp_path: Path) -> tuple[str, str]:
    _edit_json(root / "meta" / "stats.json", lambda s: s.update(origin="/srv/cluster7/runs/ep.mcap"))
    return "meta/stats.json", "/srv/cluster7/runs/ep.mcap"


@pytest.mark.parametrize("inject", [_inject_root, _inject_cwd, _inject_home, _inject_command, _inject_other_path])
def test_a_local_path_or_the_command_line_is_refused_naming_the_file(shareable, tmp_path, monkeypatch, inject):
    monkeypatch.setenv("HOME", "/home/someone")
    rel, bad = inject(shareable, tmp_path)
    out = tmp_path / "share" / "tiny"
    with pytest.raises(LocalPathError) as e:
        stage_for_sharing(shareable, out)
    msg = str(e.value)
    assert msg.startswith(f"{rel}: holds ") and repr(bad) in msg and "nothing published" in msg
    assert not (tmp_path / "share").exists()  # no copy, no staging leftovers, no created parent


def test_repo_id_is_rewritten_only_where_lerobot_stores_one(shareable, tmp_path):
    out = tmp_path / "share" / "a"
    stage_for_sharing(shareable, out, repo_id="someone/crowds")
    # lerobot 0.4.4 keeps no repo id in the dataset: info.json is the exported file itself, our side file keeps its id
    assert (out / INFO).read_bytes() == (shareable / INFO).read_bytes()
    assert json.loads((out / ICROWDNAV_META).read_text())["repo_id"] == "icrowdnav/tiny"
    assert 'LeRobotDataset("someone/crowds"' in (out / CARD).read_text()

    _edit_json(shareable / INFO, lambda i: i.update(repo_id="icrowdnav/tiny"))  # as another lerobot might store it
    out = tmp_path / "share" / "b"
    counts = stage_for_sharing(shareable, out, repo_id="someone/crowds")
    assert json.loads((out / INFO).read_text())["repo_id"] == "someone/crowds" and INFO in counts["rewritten"]


def test_bad_repo_id_or_an_out_dir_inside_the_dataset_is_a_config_error(shareable, tmp_path):
    with pytest.raises(ConfigError, match="repo_id: expected 'owner/name'"):
        stage_for_sharing(shareable, tmp_path / "share", repo_id="no-slash")
    with pytest.raises(ConfigError, match="out_dir: expected a folder outside the dataset"):
        stage_for_sharing(shareable, shareable / "share")
    with pytest.raises(ConfigError, match="out_dir"):
        stage_for_sharing(shareable, shareable.parent, overwrite=True)
    assert not (tmp_path / "share").exists() and not (shareable / "share").exists()


def test_overwrite_replaces_an_existing_copy(shareable, tmp_path):
    out = tmp_path / "share" / "tiny"
    stage_for_sharing(shareable, out)
    (out / "stale.txt").write_text("old")
    with pytest.raises(ICrowdNavError, match="already exists; pass --overwrite"):
        stage_for_sharing(shareable, out)
    stage_for_sharing(shareable, out, overwrite=True)
    assert not (out / "stale.txt").exists() and (out / CARD).is_file()


# ------------------------------------------------------------------------------------------------------------ CLI
def _missing(root: Path, tmp_path: Path) -> list[str]:
    return [str(tmp_path / "absent"), str(tmp_path / "out")]


def _not_lerobot(root: Path, tmp_path: Path) -> list[str]:
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("x")
    return [str(tmp_path / "plain"), str(tmp_path / "out")]


def _corrupt_info(root: Path, tmp_path: Path) -> list[str]:
    (root / INFO).write_text('{"codebase_version": "v3.0", "features": ')
    return [str(root), str(tmp_path / "out")]


def _out_exists(root: Path, tmp_path: Path) -> list[str]:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    return [str(root), str(tmp_path / "out")]


def _push_without_repo_id(root: Path, tmp_path: Path) -> list[str]:
    return [str(root), str(tmp_path / "out"), "--push"]


@pytest.mark.parametrize("case, expected", [
    (_missing, "error: missing dataset directory: "),
    (_not_lerobot, "is not a LeRobot dataset: missing meta/info.json"),
    (_corrupt_info, "error: corrupt LeRobot metadata "),
    (_out_exists, "already exists; pass --overwrite to replace it"),
    (_push_without_repo_id, "error: --push: expected --repo-id owner/name"),
])
def test_cli_bad_input_is_one_error_line_and_writes_nothing(shareable, tmp_path, capsys, case, expected):
    argv = case(shareable, tmp_path)
    before = _digest(tmp_path)
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and expected in err[0], err
    assert captured.out == ""
    assert _digest(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("."))\
        == []


# ----------------------------------------------------------------------------------------------------------- push
class _FakeHub:
    """Records the Hub calls of ``push_staged`` (no network)."""

    calls: list[tuple[str, dict]] = []
    fail_upload = False

    def create_repo(self, **kw):
        self.calls.append(("create_repo", kw))
        return f"https://huggingface.co/datasets/{kw['repo_id']}"

    def upload_folder(self, **kw):
        if self.fail_upload:
            raise OSError("network is unreachable")
        kw["card"] = (Path(kw["folder_path"]) / CARD).read_text()
        kw["files"] = sorted(p.relative_to(kw["folder_path"]).as_posix() for p in Path(kw["folder_path"]).rglob("*")
                             if p.is_file())
        self.calls.append(("upload_folder", kw))

    def delete_tag(self, repo_id, **kw):
        self.calls.append(("delete_tag", {"repo_id": repo_id, **kw}))

    def create_tag(self, repo_id, **kw):
        self.calls.append(("create_tag", {"repo_id": repo_id, **kw}))


def test_push_uploads_the_staged_copy_with_our_card(shareable, tmp_path, monkeypatch, capsys):
    import huggingface_hub
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    _FakeHub.calls = []
    monkeypatch.setattr(huggingface_hub, "HfApi", _FakeHub)

    def no_lerobot_push(*a, **kw):
        raise AssertionError("LeRobotDataset.push_to_hub would replace our README with lerobot's card")

    monkeypatch.setattr(LeRobotDataset, "push_to_hub", no_lerobot_push)
    out = tmp_path / "share" / "tiny"
    assert main([str(shareable), str(out), "--repo-id", "someone/crowds", "--push"]) == 0
    assert json.loads(capsys.readouterr().out)["url"] == "https://huggingface.co/datasets/someone/crowds"
    names = [c[0] for c in _FakeHub.calls]
    assert names == ["create_repo", "upload_folder", "delete_tag", "create_tag"]
    kw = dict(_FakeHub.calls)
    assert kw["create_repo"] == {"repo_id": "someone/crowds", "private": False, "repo_type": "dataset",
                                 "exist_ok": True}
    up = kw["upload_folder"]
    assert Path(up["folder_path"]) == out and up["repo_type"] == "dataset" and "images/" in up["ignore_patterns"]
    assert "## Action convention" in up["card"] and 'LeRobotDataset("someone/crowds"' in up["card"]
    assert "manifest.json" not in up["files"] and PROVENANCE in up["files"]
    assert kw["create_tag"] == {"repo_id": "someone/crowds", "tag": "v3.0", "repo_type": "dataset"}


def test_a_failed_push_is_one_error_line_and_keeps_the_copy(shareable, tmp_path, monkeypatch, capsys):
    import huggingface_hub

    monkeypatch.setattr(huggingface_hub, "HfApi", _FakeHub)
    monkeypatch.setattr(_FakeHub, "fail_upload", True)
    out = tmp_path / "share" / "tiny"
    assert main([str(shareable), str(out), "--repo-id", "someone/crowds", "--push"]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # progress log lines may precede it (logging set up by
    errors = [line for line in err if line.startswith("error:")]  # another test): one error line, no traceback
    assert len(errors) == 1 and errors[0].startswith("error: push of ") and "network is unreachable" in errors[0]
    assert not any("Traceback" in line for line in err)
    assert (out / CARD).is_file()

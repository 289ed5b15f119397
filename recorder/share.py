"""Share an exported dataset: a Hugging Face dataset card and a clean, push-ready copy.

::

    python -m recorder.share data/datasets/icrowdnav/expert data/share/expert --repo-id me/icrowdnav-expert
    python -m recorder.share data/datasets/icrowdnav/expert data/share/expert --repo-id me/icrowdnav-expert \\
        --overwrite --push [--private]

    from recorder.share import dataset_card, stage_for_sharing
    stage_for_sharing(Path("data/datasets/icrowdnav/expert"), Path("data/share/expert"), repo_id="me/expert")

An exported dataset (``icrowdnav export``, :mod:`recorder.export_stage`) holds, beside lerobot's files, the stage's
``manifest.json`` (the command line, input paths) and ``config.yaml`` (the data dir, possibly absolute). They stay
where they are (resume and verification read them); sharing goes through a staged copy instead::

    OUT_DIR/
    ├── README.md                        the dataset card (dataset_card): YAML front matter + markdown
    ├── meta/
    │   ├── info.json, stats.json, tasks.parquet, episodes/...   lerobot's, as exported
    │   ├── icrowdnav.json               ours; absolute paths in the known path fields made portable (below)
    │   ├── icrowdnav_episodes.jsonl     ours; idem
    │   └── provenance.json              git_commit, git_dirty, code_hash, config_hash, created_utc, counts
    ├── data/chunk-*/file-*.parquet      hard links to the dataset's files (copies across filesystems)
    └── videos/<key>/chunk-*/file-*.mp4  idem

No ``manifest.json``, no ``config.yaml``, no ``images/``, no dot-files. The copy is written into a staging directory
(:class:`pipeline.core.artifacts.OutputDir`) and published only after every text file in it (``*.json``,
``*.jsonl``, ``*.md``, ``*.yaml``) was scanned for local paths — the dataset's absolute path and its parent folders
up to the data dir, the working directory, ``$HOME``, an absolute ``data_dir`` and absolute arguments of the
manifest's command line, that command line itself, and any other absolute POSIX path (``/a/b``) — any hit is an
error naming the file and the string, and nothing is published. Binary files (parquet, mp4) are not scanned.

Known path fields of our side files (``sources`` of ``meta/icrowdnav.json``; ``source``, ``driver`` and
``meta.driver`` of each ``meta/icrowdnav_episodes.jsonl`` row; see :data:`PATH_FIELDS`) hold absolute paths whenever
the recording was made with an absolute data dir; in the copy such a value becomes relative to the data dir (or to
the working directory), else its file name. Relative values stay. Every other field is copied as is (and scanned).
The copy's files are hard links: treat the copy as read-only (files this module rewrites are new files, so the
dataset itself is never changed).

``repo_id``: lerobot 0.4.4 stores no repo id in the dataset (``meta/info.json`` has none; it comes from the caller
of ``LeRobotDataset``), so ``--repo-id`` changes only the card's load example and the Hub repo pushed to; a
``repo_id`` key in ``meta/info.json`` (another lerobot version) would be rewritten. ``meta/icrowdnav.json``'s own
``repo_id`` (the id the dataset was exported under) is ours and stays.

Why ``--push`` does not call ``LeRobotDataset.push_to_hub``: in lerobot 0.4.4 it uploads the folder and then, always,
builds lerobot's own card (``create_lerobot_dataset_card``: a generic template with the raw ``info.json``) and
pushes it as ``README.md``, replacing ours; no argument turns that off (``**card_kwargs`` only fill lerobot's
template). So :func:`push_staged` runs lerobot's own checks by loading the copy with stock
``LeRobotDataset(repo_id, root=OUT_DIR, video_backend="pyav")`` and then does the three Hub steps of
``push_to_hub`` itself with ``huggingface_hub.HfApi``: ``create_repo(repo_type="dataset", exist_ok=True)``,
``upload_folder`` (``images/`` ignored, as lerobot does) — one commit holding our card — and the ``v3.0`` tag
(lerobot's ``CODEBASE_VERSION``; ``LeRobotDataset(repo_id)`` resolves the Hub revision through that tag).
"""

from __future__ import annotations

import argparse
import contextlib
import fnmatch
import json
import logging
import os
import re
import shlex
import shutil
import sys
from collections import Counter
from collections.abc import Iterable
from pathlib import Path, PurePosixPath
from typing import Any

from huggingface_hub import DatasetCardData

from pipeline.core.artifacts import OutputDir, atomic_write_json, atomic_write_text
from pipeline.core.errors import (
    ConfigError,
    CorruptArtifactError,
    ICrowdNavError,
    InputMissingError,
    OutputExistsError,
    reports_errors,
)
from pipeline.core.manifest import MANIFEST_NAME, Manifest
from recorder.dataset_info import ICROWDNAV_EPISODES, ICROWDNAV_META, INFO

log = logging.getLogger("icrowdnav")

PROVENANCE = "meta/provenance.json"
CARD = "README.md"
SHARED_DIRS = ("meta", "data", "videos")  # what of the dataset folder is shared (lerobot's tree + our meta files)
TEXT_SUFFIXES = (".json", ".jsonl", ".md", ".yaml", ".yml")  # scanned for local paths
PROVENANCE_KEYS = ("git_commit", "git_dirty", "code_hash", "config_hash", "created_utc", "counts")
# our side files' fields that hold paths: (file, field path inside one record; "*" = every list item)
PATH_FIELDS: dict[str, tuple[tuple[str, ...], ...]] = {
    ICROWDNAV_META: (("sources", "*"),),
    ICROWDNAV_EPISODES: (("source",), ("driver",), ("meta", "driver")),
}

LICENSE = "apache-2.0"
TAGS = ["LeRobot", "icrowdnav", "crowd-navigation", "simulation"]
NOT_RECORDED = "not recorded"
LEROBOT_TIER = "v3."  # codebase_version prefix this module understands
PAPER_TITLE = "Learning Robot Visual Navigation in Crowds via Intention-Aware Scene Representations"
PAPER_PAGE = "https://broln7.github.io/socialbev.io/"
PAPER_BIBTEX = """@article{bao2026icrowdnav,
  title   = {Learning Robot Visual Navigation in Crowds via Intention-Aware Scene Representations},
  author  = {Bao, Han and Xia, Bingyi and Ye, Hanjing and Zhan, Yu and Cheng, Hao and Jia, Baozhi and
             Xu, Wenjun and Wang, Jiankun},
  journal = {IEEE Robotics and Automation Letters (RA-L)},
  year    = {2026},
}"""
# lerobot's own bookkeeping features (it adds them to every dataset, without a description)
LEROBOT_FEATURE_DOCS = {
    "timestamp": "time since the episode's first frame (s) = frame_index / fps",
    "frame_index": "index of the frame within its episode, from 0",
    "episode_index": "index of the episode, from 0",
    "index": "index of the frame in the whole dataset, from 0",
    "task_index": "row of meta/tasks.parquet holding the frame's task text",
}
_REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[A-Za-z0-9][\w.-]*$")
_NAME_CHARS = r"\w.~+\-"  # characters of a file name (for a regex character class)
# an absolute POSIX path of at least two parts (/a/b), not inside a URL (https://host/a/b) or a relative path (m/s)
_ABSOLUTE_PATH = re.compile(rf"(?<![{_NAME_CHARS}:/\\])/(?:[{_NAME_CHARS}]+/)+[{_NAME_CHARS}]*")
_SIZE_CATEGORIES = ((1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M"),
                    (10_000_000, "1M<n<10M"), (100_000_000, "10M<n<100M"), (1_000_000_000, "100M<n<1B"))


class LocalPathError(ICrowdNavError):
    """A file of a copy staged for sharing holds a local path or the command line that made the dataset."""


class PushError(ICrowdNavError):
    """The Hub refused or could not be reached while pushing a staged copy."""


# ------------------------------------------------------------------------------------------------- reading inputs
def _read_json(path: Path, what: str) -> Any:
    """Parsed JSON of ``path`` (which must exist); a damaged file is a :class:`CorruptArtifactError` naming it."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise CorruptArtifactError(f"corrupt {what} {path}: invalid JSON at line {e.lineno} column {e.colno} "
                                   f"({e.msg})") from None
    except (UnicodeDecodeError, IsADirectoryError) as e:
        raise CorruptArtifactError(f"corrupt {what} {path}: cannot read it as UTF-8 text ({e})") from None


def read_info(root: Path) -> dict[str, Any]:
    """``meta/info.json`` of a LeRobot v3 dataset, checked for what sharing needs.

    Raises:
        InputMissingError: ``root`` or its ``meta/info.json`` does not exist.
        CorruptArtifactError: ``meta/info.json`` is not JSON, not an object, has no ``features`` object or is not
            codebase ``v3.x``.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputMissingError(f"missing dataset directory: {root}")
    path = root / INFO
    if not path.is_file():
        raise InputMissingError(f"{root} is not a LeRobot dataset: missing {INFO}")
    info = _read_json(path, "LeRobot metadata")
    if not isinstance(info, dict):
        raise CorruptArtifactError(f"{path}: expected a JSON object, got {type(info).__name__}")
    feats = info.get("features")
    if not isinstance(feats, dict) or not all(isinstance(v, dict) for v in feats.values()):
        raise CorruptArtifactError(f"{path}: field 'features': expected an object of feature name -> "
                                   f"{{dtype, shape, names}}, got {json.dumps(feats)[:80]}")
    version = info.get("codebase_version")
    if not isinstance(version, str) or not version.startswith(LEROBOT_TIER):
        raise CorruptArtifactError(f"{path}: field 'codebase_version': expected {LEROBOT_TIER}x (LeRobot v3 "
                                   f"dataset), got {version!r}")
    return info


def _read_side(root: Path) -> tuple[dict[str, Any] | None, list[dict[str, Any]] | None]:
    """Our ``meta/icrowdnav.json`` and ``meta/icrowdnav_episodes.jsonl`` rows; None where a file is absent."""
    side = None
    path = root / ICROWDNAV_META
    if path.is_file():
        side = _read_json(path, "iCrowdNav metadata")
        if not isinstance(side, dict):
            raise CorruptArtifactError(f"{path}: expected a JSON object, got {type(side).__name__}")
    rows = None
    path = root / ICROWDNAV_EPISODES
    if path.is_file():
        rows = []
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as e:
                raise CorruptArtifactError(f"corrupt {path}: line {n}: invalid JSON ({e.msg})") from None
            if not isinstance(row, dict):
                raise CorruptArtifactError(f"{path}: line {n}: expected a JSON object, got {type(row).__name__}")
            rows.append(row)
    return side, rows


def _read_manifest(root: Path) -> Manifest | None:
    """The export stage's ``manifest.json`` beside the dataset, or None (a dataset made by ``recorder.export``)."""
    path = root / MANIFEST_NAME
    return Manifest.read(path) if path.is_file() else None


def _provenance(root: Path, manifest: Manifest | None) -> dict[str, Any] | None:
    """The shareable part of the manifest (no command line, no paths), or a staged copy's ``meta/provenance.json``."""
    if manifest is not None:
        return {k: getattr(manifest, k) for k in PROVENANCE_KEYS}
    path = root / PROVENANCE
    if path.is_file():
        prov = _read_json(path, "provenance")
        if not isinstance(prov, dict):
            raise CorruptArtifactError(f"{path}: expected a JSON object, got {type(prov).__name__}")
        return {k: prov.get(k) for k in PROVENANCE_KEYS}
    return None


# -------------------------------------------------------------------------------------------------------- the card
def _get(d: Any, *keys: str) -> Any:
    """``d[k0][k1]...`` or None where a level is missing or not a dict."""
    for k in keys:
        if not isinstance(d, dict):
            return None
        d = d.get(k)
    return d


def _cell(value: Any) -> str:
    """Text for one markdown table cell (no pipes, no line breaks)."""
    return " ".join(str(value).split()).replace("|", "\\|")


def _number(v: Any) -> str:
    """``0.1`` / ``45.7007`` / ``32``: short text for a number."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return str(v)
    return f"{v:.6g}"


def _matrix(m: list) -> str:
    """A matrix as aligned rows inside a code block."""
    cells = [[_number(v) for v in row] for row in m]
    width = max(len(c) for row in cells for c in row)
    return "```\n" + "\n".join("[" + "  ".join(c.rjust(width) for c in row) + "]" for row in cells) + "\n```"


def _is_matrix(v: Any) -> bool:
    return (isinstance(v, list) and len(v) > 0 and all(isinstance(r, list) and r for r in v)
            and all(isinstance(x, int | float) and not isinstance(x, bool) for r in v for x in r))


def _tally(values: Iterable[Any], unit: str = "") -> str:
    """``hallway (3 episodes), office (1 episode)``; ``not recorded`` when every value is missing."""
    counts = Counter(v if isinstance(v, str | int | float) else json.dumps(v) for v in values
                     if v is not None and v != "")
    if not counts:
        return NOT_RECORDED
    keys = sorted(counts, key=lambda v: (str(type(v)), v))
    return ", ".join(f"{_number(v)}{unit} ({counts[v]} episode{'s' if counts[v] != 1 else ''})" for v in keys)


def _description(name: str, feature: dict[str, Any], side: dict[str, Any] | None) -> str:
    """A feature's description: its ``info.description`` (format 2), our format-1 side file's, lerobot's index
    features', else ``not recorded``."""
    text = _get(feature, "info", "description")
    if isinstance(text, str) and text.strip():
        return text
    if name in LEROBOT_FEATURE_DOCS:
        return LEROBOT_FEATURE_DOCS[name]
    docs = _get(side, "spec", "features")
    if isinstance(docs, dict):
        for pattern, doc in docs.items():
            if isinstance(doc, str) and (pattern == name or fnmatch.fnmatchcase(name, pattern)):
                return doc
    return NOT_RECORDED


def _dtype(feature: dict[str, Any]) -> str:
    dtype = feature.get("dtype", NOT_RECORDED)
    codec, pix = _get(feature, "info", "video.codec"), _get(feature, "info", "video.pix_fmt")
    if dtype == "video" and codec:
        return f"video ({codec}{', ' + str(pix) if pix else ''})"
    return str(dtype)


def _shape(feature: dict[str, Any]) -> str:
    shape = feature.get("shape")
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")" \
        if isinstance(shape, list | tuple) else NOT_RECORDED


def _names(feature: dict[str, Any]) -> str:
    names = feature.get("names")
    if isinstance(names, list):
        return ", ".join(str(n) for n in names)
    if isinstance(names, dict):
        return "; ".join(f"{k}: {', '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in names.items())
    return ""


def _cameras(features: dict[str, dict[str, Any]]) -> list[str]:
    cams = set()
    for key in features:
        for prefix in ("observation.images.", "observation.depth."):
            if key.startswith(prefix) and key[len(prefix):]:
                cams.add(key[len(prefix):])
    return sorted(cams)


def _camera_section(cam: str, features: dict[str, dict[str, Any]], side: dict[str, Any] | None) -> list[str]:
    keys = [k for k in (f"observation.images.{cam}", f"observation.depth.{cam}") if k in features]
    model = next((m for m in (_get(features[k], "info", "camera") for k in keys) if isinstance(m, dict)), None)
    source = "meta/info.json"
    if model is None and isinstance(_get(side, "cameras", cam), dict):
        model, source = side["cameras"][cam], ICROWDNAV_META  # format 1 kept the camera model in our side file
    out = [f"### `{cam}`", "", "Features: " + ", ".join(f"`{k}`" for k in keys) + ".", ""]
    w, h = _get(model, "width"), _get(model, "height")
    if w is None or h is None:
        shape = next((features[k].get("shape") for k in keys if isinstance(features[k].get("shape"), list)), None)
        if shape and len(shape) >= 2:
            h, w = shape[0], shape[1]
    out.append(f"- Image size: {w} x {h} px (width x height)" if w is not None and h is not None
               else f"- Image size: {NOT_RECORDED}")
    depth = _get(features.get(f"observation.depth.{cam}"), "info")
    encoding = {k: v for k, v in (depth or {}).items() if k in ("unit", "scale_to_m", "invalid_value")}
    if encoding:
        out.append("- Depth encoding: " + ", ".join(f"`{k}` = {_cell(v)}" for k, v in encoding.items()))
    if model is None:
        out.append(f"- Intrinsics and extrinsics: {NOT_RECORDED}")
        return out + [""]
    k_mat = model.get("K")
    if _is_matrix(k_mat):
        out += ["- Intrinsics `K` (pixels; u = fx x/z + cx, v = fy y/z + cy, camera frame):", "", _matrix(k_mat), ""]
    else:
        out.append(f"- Intrinsics `K`: {NOT_RECORDED}")
    extr = [k for k in model if k.startswith("T_") and _is_matrix(model[k])]
    for key in extr:
        what = ("the camera's pose in the robot base frame: p_base = T_base_cam p_cam"
                if key == "T_base_cam" else "4 x 4 homogeneous transform")
        out += [f"- Extrinsics `{key}` ({what}):", "", _matrix(model[key]), ""]
    if not extr:
        out.append(f"- Extrinsics: {NOT_RECORDED}")
    rest = [k for k in model if k not in ("K", "width", "height", "name", *extr)]
    for key in rest:
        value = model[key]
        out.append(f"- `{key}`: " + ("\n\n" + _matrix(value) + "\n" if _is_matrix(value)
                                     else _cell(json.dumps(value) if not isinstance(value, str) else value)))
    out += ["", f"(from `{source}`)", ""]
    return out


def _size_category(frames: Any) -> list[str] | None:
    if not isinstance(frames, int):
        return None
    return [next((label for limit, label in _SIZE_CATEGORIES if frames < limit), "n>1T")]


def _front_matter(info: dict[str, Any], repo_id: str) -> str:
    """YAML front matter as lerobot's ``create_lerobot_dataset_card`` makes it (huggingface_hub's
    ``DatasetCardData``), with our tags, a pretty name and the size category."""
    data = DatasetCardData(
        license=LICENSE,
        tags=list(TAGS),
        task_categories=["robotics"],
        pretty_name=f"iCrowdNav simulated crowd navigation ({repo_id})",
        size_categories=_size_category(info.get("total_frames")),
        configs=[{"config_name": "default", "data_files": "data/*/*.parquet"}],
    )
    return "---\n" + data.to_yaml() + "\n---\n"


def dataset_card(root: Path, *, repo_id: str | None = None) -> str:
    """The Hugging Face dataset card (``README.md``) of an exported iCrowdNav dataset.

    Reads ``meta/info.json`` (features with their ``info.description``, cameras' ``info.camera``, the action's
    ``info.convention`` and ``info.icrowdnav_format``), ``meta/icrowdnav.json`` and ``meta/icrowdnav_episodes.jsonl``
    (scenes, densities, drivers, outcomes, lengths; format-1 descriptions and camera models) and the export's
    ``manifest.json`` (or a staged copy's ``meta/provenance.json``) for the code version. Whatever is missing reads
    ``not recorded``.

    Args:
        root: the dataset directory.
        repo_id: the Hub repo id for the load example (default: the id the dataset was exported under).

    Returns:
        Markdown with YAML front matter (license, task_categories, tags, configs as lerobot writes them).

    Raises:
        InputMissingError, CorruptArtifactError: ``root`` is not a readable LeRobot v3 dataset, or one of the
            side files / the manifest exists but is damaged.
    """
    root = Path(root)
    info = read_info(root)
    side, rows = _read_side(root)
    manifest = _read_manifest(root)
    prov = _provenance(root, manifest)
    repo_id = (repo_id or _get(side, "repo_id") or (manifest.params.get("repo_id") if manifest else None)
               or "<owner>/<name>")
    features: dict[str, dict[str, Any]] = info["features"]
    fps = info.get("fps")
    action = features.get("action", {})
    fmt = _get(action, "info", "icrowdnav_format") or _get(side, "format_version") or NOT_RECORDED

    if rows:
        n_episodes = len(rows)
        lengths = [r.get("length") for r in rows]
        n_frames = sum(lengths) if all(isinstance(n, int) for n in lengths) else info.get("total_frames")
    else:
        n_episodes, n_frames = info.get("total_episodes"), info.get("total_frames")
    rows = rows or []
    duration = (f"{n_frames / fps:.1f} s" if isinstance(n_frames, int) and isinstance(fps, int | float) and fps > 0
                else NOT_RECORDED)
    renderers = sorted({str(r) for r in (_get(row, "meta", "renderer") for row in rows) if r})

    md = [_front_matter(info, repo_id)]
    md += [
        "# iCrowdNav: simulated robot navigation in crowds", "",
        "Episodes of a differential-drive robot with two RGB-D cameras driving to a goal among pedestrians whose "
        "head and torso turn before they do (the pedestrians announce their turns), simulated with "
        "[pybullet](https://pybullet.org). Each frame holds both cameras' RGB (video) and depth, the robot's state, "
        "odometry and goal, the detected people's 3-D poses, the command sent, the reward, and privileged simulator "
        "state (every pedestrian's state, keypoints and pending goal; a local occupancy map) for training teachers "
        "and encoders. It is the data of the iCrowdNav reproduction of the paper below, stored as a "
        f"[LeRobot](https://github.com/huggingface/lerobot) {info.get('codebase_version')} dataset.", "",
        f"- **Paper:** {PAPER_TITLE} (IEEE Robotics and Automation Letters, 2026); project page {PAPER_PAGE}",
        "- **License:** Apache-2.0",
        f"- **Robot type:** `{info.get('robot_type', NOT_RECORDED)}`",
        f"- **Task:** {_get(side, 'task') or NOT_RECORDED}",
        f"- **iCrowdNav dataset format:** {fmt}", "",
        "## How it was recorded", "",
        "Every episode was driven in the simulator, logged as one MCAP file, and exported from the complete logs "
        "into this dataset (validated before it was published).", "",
        "- **Simulator:** pybullet" + (f"; renderer {', '.join(renderers)}" if renderers else ""),
        f"- **Driver:** {_tally(r.get('driver') for r in rows)}",
        f"- **Scenes:** {_tally(r.get('scene') for r in rows)}",
        f"- **Crowd densities:** {_tally((r.get('density') for r in rows), ' ped/m²')}",
        f"- **Episode ends:** {_tally(r.get('outcome') for r in rows)}",
        f"- **Episodes:** {n_episodes if n_episodes is not None else NOT_RECORDED}; "
        f"**frames:** {n_frames if n_frames is not None else NOT_RECORDED}; "
        f"**fps:** {_number(fps) if fps is not None else NOT_RECORDED}"
        + (f" ({duration} in all)" if duration != NOT_RECORDED else ""), "",
        "Per-episode facts (scene, density, seeds, driver, outcome, return, start and goal, camera model) are in "
        f"`{ICROWDNAV_EPISODES}`, one JSON row per `episode_index`; dataset-wide facts in `{ICROWDNAV_META}`; "
        f"the code version in `{PROVENANCE}`. Stock lerobot ignores these files.", "",
        "## Features", "",
        "| feature | dtype | shape | axes | description (units, frame) |",
        "|---|---|---|---|---|",
    ]
    md += [f"| `{name}` | {_cell(_dtype(ft))} | {_shape(ft)} | {_cell(_names(ft))} | "
           f"{_cell(_description(name, ft, side))} |" for name, ft in features.items()]
    frames = _get(side, "spec", "frames")
    if isinstance(frames, dict) and frames:
        md += ["", "Coordinate frames:", ""] + [f"- **{k}:** {_cell(v)}" for k, v in frames.items()]
    md += ["", "## Action convention", ""]
    convention = _get(action, "info", "convention")
    if isinstance(convention, str) and convention.strip():
        md.append(convention.strip())
    else:
        md.append(f"{NOT_RECORDED.capitalize()} in `meta/info.json` (iCrowdNav dataset format {fmt}).")
        described = _description("action", action, side) if action else NOT_RECORDED
        if described != NOT_RECORDED:
            md.append(f"The `action` feature's description reads: \"{_cell(described)}\".")
    if action:
        md += ["", f"`action`: {_dtype(action)} {_shape(action)}, axes {_names(action) or NOT_RECORDED}."]
    md += ["", "## Cameras", ""]
    cams = _cameras(features)
    for cam in cams:
        md += _camera_section(cam, features, side)
    if not cams:
        md += [f"Camera model: {NOT_RECORDED}.", ""]
    md += [
        "## Loading", "",
        "```python",
        "from lerobot.datasets.lerobot_dataset import LeRobotDataset",
        "",
        f'ds = LeRobotDataset("{repo_id}", video_backend="pyav")  # from the Hub',
        f'ds = LeRobotDataset("{repo_id}", root="path/to/this/folder", video_backend="pyav")  # a local copy',
        "```", "",
        "Use `video_backend=\"pyav\"`: lerobot 0.4.4's default torchcodec backend needs system FFmpeg libraries and, "
        "with DataLoader workers, fails if the dataset was read in the main process first.", "",
        "## License", "",
        "Apache-2.0 (https://www.apache.org/licenses/LICENSE-2.0).", "",
        "## Citation", "",
        "```bibtex", PAPER_BIBTEX, "```", "",
    ]
    if prov is not None:
        commit = prov.get("git_commit") or NOT_RECORDED
        dirty = " with uncommitted changes" if prov.get("git_dirty") else ""
        md.append(f"Recorded and exported with the iCrowdNav pipeline at code version `{commit}`{dirty} "
                  f"(code hash `{prov.get('code_hash') or NOT_RECORDED}`; export config hash "
                  f"`{prov.get('config_hash') or NOT_RECORDED}`; exported {prov.get('created_utc') or NOT_RECORDED}"
                  f"); see `{PROVENANCE}`.")
    else:
        md.append(f"Recorded and exported with the iCrowdNav pipeline; code version {NOT_RECORDED} (no "
                  f"{MANIFEST_NAME} beside the dataset).")
    return "\n".join(md) + "\n"


# ------------------------------------------------------------------------------------------- the push-ready copy
def _check_repo_id(repo_id: str | None, what: str = "repo_id") -> None:
    if repo_id is not None and (not _REPO_ID.match(repo_id) or ".." in repo_id.split("/")):
        raise ConfigError(f"{what}: expected 'owner/name' (letters, digits, ._-), got {repo_id!r}")


def _data_dir(root: Path, manifest: Manifest | None) -> Path | None:
    """The data dir holding the dataset (``DATA_DIR/datasets/<owner>/<name>``), absolute, or None."""
    for parent in root.parents:
        if parent.name == "datasets":
            return parent.parent
    if manifest is not None and isinstance(manifest.params.get("data_dir"), str):
        return Path(manifest.params["data_dir"]).absolute()
    return None


def _local_strings(root: Path, manifest: Manifest | None) -> list[tuple[str, str]]:
    """``(string, what it is)`` that must not appear in a shared file."""
    out: dict[str, str] = {}

    def add(p: Path | str | None, why: str, min_parts: int = 1) -> None:
        if not p:
            return
        p = Path(p)
        if len(p.parts) > min_parts and str(p) not in out:  # never "/" (and, for parents, never "/tmp")
            out[str(p)] = why

    for r in (root.absolute(), root.resolve()):
        add(r, "the dataset's absolute path")
        data_dir = _data_dir(r, manifest)
        for parent in r.parents:
            add(parent, "a parent folder of the dataset", min_parts=2)
            if data_dir is None or parent == data_dir:
                break
    add(_data_dir(root.absolute(), manifest), "the data dir")
    add(Path.cwd(), "the working directory")
    add(Path.cwd().resolve(), "the working directory")
    add(os.environ.get("HOME"), "$HOME")
    if manifest is not None:
        data_dir = manifest.params.get("data_dir")
        if isinstance(data_dir, str) and os.path.isabs(data_dir):
            add(data_dir, "the config's data_dir")
        for arg in manifest.command:
            if os.path.isabs(arg):
                add(arg, "an argument of the command line that made the dataset")
    found = sorted(out.items(), key=lambda kv: -len(kv[0]))  # the most specific first
    if manifest is not None and len(manifest.command) >= 3:
        found += [(shlex.join(manifest.command), "the command line that made the dataset"),
                  (" ".join(manifest.command), "the command line that made the dataset")]
    return found


def _scan(path: Path, local: list[tuple[str, str]]) -> tuple[str, str] | None:
    """``(offending string, what it is)`` of the first local path or command line in a text file, or None."""
    text = path.read_text(encoding="utf-8", errors="replace")
    for s, why in local:
        if why.startswith("the command line"):
            if s in text:
                return s, why
        elif re.search(rf"(?<![{_NAME_CHARS}]){re.escape(s)}(?![{_NAME_CHARS}])", text):
            return s, why
    m = _ABSOLUTE_PATH.search(text)
    if m:
        return m.group(0), "an absolute path"
    return None


def _portable(value: Any, bases: list[Path]) -> Any:
    """An absolute path made relative to the first of ``bases`` holding it, else its file name; anything else
    unchanged."""
    if not isinstance(value, str) or not (os.path.isabs(value) or value.startswith("~")):
        return value
    p = Path(value)
    for base in bases:
        with contextlib.suppress(ValueError):
            return p.relative_to(base).as_posix()
    return PurePosixPath(value.replace("\\", "/")).name


def _sanitize_record(record: Any, fields: tuple[tuple[str, ...], ...], bases: list[Path]) -> Any:
    def walk(node: Any, path: tuple[str, ...]) -> Any:
        if not path:
            return _portable(node, bases)
        head, rest = path[0], path[1:]
        if head == "*" and isinstance(node, list):
            return [walk(v, rest) for v in node]
        if isinstance(node, dict) and head in node:
            return {**node, head: walk(node[head], rest)}
        return node

    for f in fields:
        record = walk(record, f)
    return record


def _make_portable(staged: Path, bases: list[Path]) -> list[str]:
    """Rewrites absolute paths in the known path fields of our side files in the staged copy; the files it
    changed."""
    changed = []
    meta = staged / ICROWDNAV_META
    if meta.is_file():
        data = json.loads(meta.read_text(encoding="utf-8"))
        new = _sanitize_record(data, PATH_FIELDS[ICROWDNAV_META], bases)
        if new != data:
            atomic_write_json(meta, new)  # a new file: the dataset's (hard-linked) original is untouched
            changed.append(ICROWDNAV_META)
    eps = staged / ICROWDNAV_EPISODES
    if eps.is_file():
        rows = [json.loads(line) for line in eps.read_text(encoding="utf-8").splitlines() if line.strip()]
        new_rows = [_sanitize_record(r, PATH_FIELDS[ICROWDNAV_EPISODES], bases) for r in rows]
        if new_rows != rows:
            atomic_write_text(eps, "".join(json.dumps(r) + "\n" for r in new_rows))
            changed.append(ICROWDNAV_EPISODES)
    return changed


def _shared_files(root: Path) -> list[Path]:
    """The dataset's files to share, relative to ``root``: everything under ``meta/``, ``data/``, ``videos/`` but
    dot-files (temporary files of an interrupted write)."""
    out = []
    for d in SHARED_DIRS:
        for p in sorted((root / d).rglob("*")):
            rel = p.relative_to(root)
            if p.is_file() and not any(part.startswith(".") for part in rel.parts):
                out.append(rel)
    return out


def stage_for_sharing(root: Path, out_dir: Path, *, repo_id: str | None = None,
                      overwrite: bool = False) -> dict[str, Any]:
    """Writes a push-ready copy of an exported dataset into ``out_dir``, atomically (see the module docstring for
    the tree and for what is rewritten).

    Args:
        root: the exported dataset directory (``DATA_DIR/datasets/<owner>/<name>``).
        out_dir: the copy to create; outside ``root``.
        repo_id: the Hub repo id the copy is for (``owner/name``): the card's load example, and ``repo_id`` in
            ``meta/info.json`` if lerobot stored one (0.4.4 does not).
        overwrite: replace an existing ``out_dir`` (the old copy stays until the new one is complete).

    Returns:
        ``{"files", "bytes", "linked", "rewritten"}``: files and bytes in the copy, how many are hard links to the
        dataset's files, and which files had absolute paths made portable.

    Raises:
        InputMissingError: ``root``, its ``meta/info.json`` or ``data/`` does not exist.
        CorruptArtifactError: ``meta/info.json``, a side file or ``manifest.json`` is damaged.
        ConfigError: bad ``repo_id``; ``out_dir`` overlaps ``root``.
        OutputExistsError: ``out_dir`` exists and ``overwrite`` is False.
        LocalPathError: a file of the copy holds a local path or the command line (nothing is published).
    """
    root, out_dir = Path(root), Path(out_dir)
    _check_repo_id(repo_id)
    info = read_info(root)
    if not (root / "data").is_dir():
        raise InputMissingError(f"{root} is not a LeRobot dataset: missing data/ (the frames' parquet files)")
    _read_side(root)  # damaged side files fail here, before anything is written
    manifest = _read_manifest(root)
    prov = _provenance(root, manifest)
    if manifest is None:
        log.warning("%s has no %s: the copy records no code version (meta/provenance.json holds nulls)", root,
                    MANIFEST_NAME)
    src, dst = root.resolve(), out_dir.resolve()
    if dst == src or src in dst.parents or dst in src.parents:
        raise ConfigError(f"out_dir: expected a folder outside the dataset {root} (and not holding it), got "
                          f"{out_dir}")
    if not overwrite and (out_dir.is_file() or (out_dir.is_dir() and any(out_dir.iterdir()))):
        raise OutputExistsError(f"output directory {out_dir} already exists; pass --overwrite to replace it")
    local = _local_strings(root, manifest)
    data_dir = _data_dir(root.absolute(), manifest)
    bases = [b for b in (data_dir, Path.cwd()) if b is not None]
    bases += [b.resolve() for b in bases]

    linked = 0
    can_link = True
    with OutputDir(out_dir, "overwrite" if overwrite else "new") as od:
        staged = od.path
        for rel in _shared_files(root):
            target = staged / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            if can_link:
                try:
                    os.link(root / rel, target)
                    linked += 1
                    continue
                except OSError:  # another filesystem, or links not allowed: copy from now on
                    can_link = False
            shutil.copy2(root / rel, target)
        rewritten = _make_portable(staged, bases)
        if repo_id and "repo_id" in info:  # lerobot 0.4.4 keeps none in info.json; another version might
            info["repo_id"] = repo_id
            atomic_write_text(staged / INFO, json.dumps(info, indent=4, ensure_ascii=False))
            rewritten.append(INFO)
        atomic_write_json(staged / PROVENANCE, prov if prov is not None else dict.fromkeys(PROVENANCE_KEYS))
        card_repo = repo_id or (manifest.params.get("repo_id") if manifest else None)
        atomic_write_text(staged / CARD, dataset_card(staged, repo_id=card_repo))
        files = sorted(p for p in staged.rglob("*") if p.is_file())
        # the dataset's files first, the card (made from them) last, so that an error names the file to fix
        for p in sorted(files, key=lambda p: (p.name == CARD, p.relative_to(staged).as_posix() == PROVENANCE, p)):
            if p.suffix in TEXT_SUFFIXES:
                rel = p.relative_to(staged).as_posix()
                hit = _scan(p, local)
                if hit is not None:
                    raise LocalPathError(f"{rel}: holds {hit[1]} {hit[0]!r} (from {root / rel}); a shared dataset "
                                         f"must hold no local paths or command lines; nothing published to "
                                         f"{out_dir}")
        counts = {"files": len(files), "bytes": sum(p.stat().st_size for p in files), "linked": linked,
                  "rewritten": rewritten}
    log.info("staged %d files (%d bytes, %d hard links) for sharing -> %s", counts["files"], counts["bytes"],
             linked, out_dir)
    return counts


# ----------------------------------------------------------------------------------------------------------- push
def push_staged(out_dir: Path, repo_id: str, *, private: bool = False) -> str:
    """Uploads a copy made by :func:`stage_for_sharing` to the Hugging Face Hub as dataset ``repo_id``, keeping its
    ``README.md`` (see the module docstring for why this is not ``LeRobotDataset.push_to_hub``).

    Args:
        out_dir: the staged copy.
        repo_id: ``owner/name`` on the Hub.
        private: create the repo private (an existing repo keeps its visibility).

    Returns:
        The dataset's Hub URL.

    Raises:
        ConfigError: bad ``repo_id``.
        CorruptArtifactError: stock lerobot cannot load the copy, or it is not a staged copy (no card).
        LocalPathError: a text file of the copy holds a local path.
        PushError: the Hub refused or could not be reached.
    """
    from huggingface_hub import HfApi  # lazy: only --push talks to the Hub
    from huggingface_hub.errors import RevisionNotFoundError
    from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset  # lazy: imports torch

    out_dir = Path(out_dir)
    _check_repo_id(repo_id)
    read_info(out_dir)
    if not (out_dir / CARD).is_file() or (out_dir / MANIFEST_NAME).exists():
        raise CorruptArtifactError(f"{out_dir}: expected a copy made by stage_for_sharing ({CARD}, no "
                                   f"{MANIFEST_NAME}); run `python -m recorder.share DATASET_DIR {out_dir}` first")
    local = _local_strings(out_dir, None)
    for p in sorted(out_dir.rglob("*")):
        if p.is_file() and p.suffix in TEXT_SUFFIXES:
            rel = p.relative_to(out_dir).as_posix()
            hit = _scan(p, local)
            if hit is not None:
                raise LocalPathError(f"{out_dir / rel}: holds {hit[1]} {hit[0]!r}; nothing pushed")
    try:
        ds = LeRobotDataset(repo_id, root=out_dir, video_backend="pyav")  # lerobot's own checks of the copy
    except Exception as e:  # lerobot raises many types; the message names the copy
        raise CorruptArtifactError(f"stock lerobot cannot load the staged copy {out_dir}: "
                                   f"{type(e).__name__}: {e}") from e
    log.info("lerobot loads %s: %d episodes, %d frames; pushing to %s", out_dir, ds.num_episodes, len(ds), repo_id)
    api = HfApi()
    try:
        url = api.create_repo(repo_id=repo_id, private=private, repo_type="dataset", exist_ok=True)
        api.upload_folder(repo_id=repo_id, folder_path=out_dir, repo_type="dataset", ignore_patterns=["images/"],
                          commit_message="iCrowdNav dataset (recorder.share)")
        with contextlib.suppress(RevisionNotFoundError):
            api.delete_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
        api.create_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
    except OSError as e:  # huggingface_hub's HTTP errors and requests' connection errors are OSErrors
        raise PushError(f"push of {out_dir} to the Hub dataset {repo_id} failed: {type(e).__name__}: {e}; the "
                        "staged copy stays, run again with --push") from e
    return str(url)


@reports_errors
def main(argv: list[str] | None = None) -> int:
    """``python -m recorder.share DATASET_DIR OUT_DIR [--repo-id owner/name] [--overwrite] [--push] [--private]``."""
    ap = argparse.ArgumentParser(prog="python -m recorder.share", description=__doc__.split("\n")[0])
    ap.add_argument("dataset_dir", type=Path, help="an exported dataset (e.g. data/datasets/icrowdnav/expert)")
    ap.add_argument("out_dir", type=Path, help="the push-ready copy to create")
    ap.add_argument("--repo-id", default=None, help="Hub repo id owner/name the copy is for (needed by --push)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing OUT_DIR")
    ap.add_argument("--push", action="store_true", help="upload OUT_DIR to the Hugging Face Hub as --repo-id")
    ap.add_argument("--private", action="store_true", help="with --push: create the Hub repo private")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if args.push and not args.repo_id:
        raise ConfigError("--push: expected --repo-id owner/name (the Hub dataset to push to), got none")
    if args.private and not args.push:
        raise ConfigError("--private: only meaningful with --push")
    counts = stage_for_sharing(args.dataset_dir, args.out_dir, repo_id=args.repo_id, overwrite=args.overwrite)
    if args.push:
        counts["url"] = push_staged(args.out_dir, args.repo_id, private=args.private)
    print(json.dumps(counts))
    return 0


if __name__ == "__main__":
    sys.exit(main())

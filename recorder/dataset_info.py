"""What our readers need from an exported dataset's ``meta/info.json``, read in one place and checked.

Every stage that reads a dataset (pretraining, the ViNT-style baseline, the intention probe) goes through
:func:`read_dataset_info`: lerobot's ``info.json`` (the feature spec, fps) plus the ``info`` dicts the export adds to
its features — the dataset format (``features["action"]["info"]["icrowdnav_format"]``), each camera's
intrinsics/extrinsics (``features["observation.images.<cam>"]["info"]["camera"]``) and the occupancy crop's layout
(``features["privileged.local_occupancy"]["info"]["layout"]``). They live there, not in our ``meta/icrowdnav*`` side
files, because lerobot's dataset tools (``delete_episodes``, ``remove_feature``, ``merge_datasets``) carry
features' ``info`` over and drop unknown files. A dataset written by an older export (format 1: ``action[t]`` = the
command that *led to* frame ``t``, float32 depth, bool pose mask) is refused with a named error saying how to
re-export it from its MCAP recording — reading it with today's code would shift every action by one step.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.core.errors import CorruptArtifactError, InputMissingError
from pipeline.core.keys import ACTION, PRIV_LOCAL_OCCUPANCY, image_key
from recorder.features import FORMAT_KEY, FORMAT_VERSION

INFO = "meta/info.json"  # lerobot's
ICROWDNAV_META = "meta/icrowdnav.json"  # ours, optional extras (recorder.export writes them; lerobot's tools drop them)
ICROWDNAV_EPISODES = "meta/icrowdnav_episodes.jsonl"
IMAGE_PREFIX = image_key("")


class DatasetFormatError(CorruptArtifactError):
    """A dataset written by another version of the export (names the file, the field, expected and actual)."""


@dataclass(frozen=True)
class DatasetInfo:
    """A dataset's metadata as our readers use it.

    Attributes:
        root: the dataset directory.
        info: lerobot's ``meta/info.json``.
        fps: frames per second.
        cameras: per camera name (``left``, ``right``, in the file's order), its ``CameraSpec.to_dict()``.
        local_map: the ``privileged.local_occupancy`` layout (``LocalMapSpec.to_dict()``), None without it.
    """

    root: Path
    info: dict[str, Any]
    fps: int
    cameras: dict[str, dict[str, Any]]
    local_map: dict[str, Any] | None

    @property
    def features(self) -> dict[str, dict[str, Any]]:
        return self.info["features"]

    @property
    def repo_id(self) -> str:
        """``owner/name`` from the directory (``.../<owner>/<name>``; lerobot 0.4.4 does not store it)."""
        return f"{self.root.parent.name}/{self.root.name}"


def read_dataset_info(root: Path) -> DatasetInfo:
    """Reads and checks ``root/meta/info.json``.

    Raises:
        InputMissingError: no dataset at ``root``.
        CorruptArtifactError: unreadable JSON or no ``features``/``fps`` (names the file).
        DatasetFormatError: the dataset was written by another version of the export, or lacks our ``info``
            annotations (names the file, the field, the expected and the found value, and the re-export command).
    """
    root = Path(root)
    path = root / INFO
    if not path.is_file():
        raise InputMissingError(f"no LeRobot dataset at {root} (missing {INFO}); make it with `make record` "
                                "(icrowdnav record + export)")
    try:
        info = json.loads(path.read_text())
        features, fps = info["features"], int(info["fps"])
        if not isinstance(features, dict):
            raise TypeError(f"'features' is a {type(features).__name__}")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise CorruptArtifactError(f"{path}: unreadable dataset metadata ({type(e).__name__}: {e})") from None
    found = ((features.get(ACTION) or {}).get("info") or {}).get(FORMAT_KEY)
    if found != FORMAT_VERSION:
        was = ("no format (an export before format 2: action[t] = the command that led to frame t)"
               if found is None else repr(found))
        raise DatasetFormatError(
            f"{path}: field 'features.{ACTION}.info.{FORMAT_KEY}': expected {FORMAT_VERSION}, got {was}; re-export "
            f"the dataset from its MCAP recording: `icrowdnav export --overwrite` (or `python -m recorder.export "
            f"RAW_DIR {root} --repo-id {root.parent.name}/{root.name} --overwrite`)")
    cameras: dict[str, dict[str, Any]] = {}
    for name, ft in features.items():
        if ft.get("dtype") == "video" and name.startswith(IMAGE_PREFIX):
            cam = (ft.get("info") or {}).get("camera")
            if not isinstance(cam, dict):
                raise DatasetFormatError(f"{path}: field 'features.{name}.info.camera': expected the camera's "
                                         f"intrinsics/extrinsics, got {cam!r:.80}")
            cameras[name[len(IMAGE_PREFIX):]] = cam
    layout = ((features.get(PRIV_LOCAL_OCCUPANCY) or {}).get("info") or {}).get("layout")
    return DatasetInfo(root, info, fps, cameras, layout if isinstance(layout, dict) else None)

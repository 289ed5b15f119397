"""Tests of recorder.mcap_io: round trip, determinism, kill/signal safety, truncation, CRC damage, recovery."""

from __future__ import annotations

import hashlib
import json
import os
import queue
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from mcap.reader import make_reader

from pipeline.core.errors import CorruptArtifactError, InputMissingError, OutputExistsError
from recorder import mcap_io
from recorder.doctor_mcap import check_mcap_dir
from recorder.drive import drive_episode
from recorder.mcap_io import (
    LIBRARY,
    EpisodeReader,
    EpisodeWriter,
    Interrupted,
    count_frames,
    episode_summary,
    frame_topics,
    graceful_signals,
    read_episode,
    recover,
)
from recorder.schema import (
    CAMERA_NAMES,
    METADATA_EPISODE,
    TOPIC_CALIB,
    TOPIC_DEPTH,
    TOPIC_KEYPOINTS_2D,
    Frame,
)
from tests.recorder.helpers_mcap import record_episode, rewrite, tiny_config

REPO = Path(__file__).resolve().parents[2]
CHUNK = 60_000  # ~2 tiny frames per chunk: several chunks per episode
MSGS_PER_FRAME = len(frame_topics())  # 16; frame 0 has the occupancy grid too
DEPTH_TOL_M = 0.5e-3 + 1e-6  # mm quantisation (+ float32 rounding)


def sha256(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def assert_frames_equal(a: Frame, b: Frame, depth_tol: float = 0.0) -> None:
    """Field by field: arrays exact (dtype and shape too), depth within ``depth_tol`` m."""
    for name, va in a.__dict__.items():
        vb = getattr(b, name)
        if name in ("rgb", "depth"):
            assert set(va) == set(vb), name
            for cam in va:
                x, y = np.asarray(va[cam]), np.asarray(vb[cam])
                assert x.shape == y.shape, (name, cam)
                if name == "rgb":
                    assert y.dtype == np.uint8 and np.array_equal(x, y), (name, cam)
                else:
                    assert y.dtype == np.float32
                    assert np.max(np.abs(x.astype(np.float64) - y)) <= depth_tol, (name, cam)
                    assert np.array_equal(x == 0, y == 0), "invalid depth must stay 0 and valid depth non-zero"
        elif isinstance(va, np.ndarray):
            assert isinstance(vb, np.ndarray) and va.dtype == vb.dtype and va.shape == vb.shape, name
            assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), name
        elif isinstance(va, float) and np.isnan(va):
            assert np.isnan(vb), name
        else:
            assert va == vb, (name, va, vb)


@pytest.fixture(scope="module")
def episode():
    """The tiny episode of seed 1 in memory: (meta, occupancy, frames)."""
    ep = drive_episode(tiny_config(), 1)
    return ep.meta, ep.occupancy, list(ep.frames)


@pytest.fixture(scope="module")
def recorded(episode, tmp_path_factory) -> Path:
    meta, occ, frames = episode
    path = tmp_path_factory.mktemp("rec") / "ep.mcap"
    with EpisodeWriter(path, meta, occ, chunk_size=CHUNK) as w:
        for fr in frames:
            w.add(fr)
    return path


def chunk_layout(path: Path) -> list[tuple[int, int, int, int]]:
    """(start offset, record length, first log time, last log time) of each chunk, from the summary."""
    with open(path, "rb") as f:
        summ = make_reader(f).get_summary()
    return sorted((c.chunk_start_offset, c.chunk_length, c.message_start_time, c.message_end_time)
                  for c in summ.chunk_indexes)


# ---------------------------------------------------------------------------------------------------- round trip


def test_round_trip(episode, recorded: Path) -> None:
    meta, occ, frames = episode
    assert sum(fr.pose_mask.any() for fr in frames) > 0, "the fixture episode should contain detections"
    got_meta, got_occ, it = read_episode(recorded)
    got = list(it)
    assert got_meta == meta
    assert got_occ.dtype == bool and np.array_equal(got_occ, occ)
    assert len(got) == len(frames) == count_frames(recorded)
    for a, b in zip(frames, got, strict=True):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    s = episode_summary(recorded)
    assert s["n_frames"] == len(frames) and s["done"] and s["outcome"] == frames[-1].outcome
    assert s["duration_s"] == pytest.approx(frames[-1].t_ns / 1e9)
    assert s["topics"]["/map/occupancy"] == 1 and s["topics"]["/tf"] == len(frames)


def test_channels_use_foxglove_schemas_and_json_schemas(episode, recorded: Path) -> None:
    meta, _, frames = episode
    with open(recorded, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summ = reader.get_summary()
        schema_of = {ch.topic: summ.schemas[ch.schema_id] for ch in summ.channels.values()}
        enc_of = {ch.topic: ch.message_encoding for ch in summ.channels.values()}
        md = {m.name: m.metadata for m in reader.iter_metadata()}
        msgs = {(ch.topic, m.log_time): m.data for _, ch, m in reader.iter_messages()}
    assert header.library == LIBRARY  # constant: no version or time in the header
    assert md[METADATA_EPISODE] == meta.to_metadata()
    for cam in CAMERA_NAMES:
        assert schema_of[f"/camera/{cam}/image"].name == "foxglove.RawImage"
        assert schema_of[f"/camera/{cam}/depth"].name == "foxglove.RawImage"
        assert schema_of[f"/camera/{cam}/calibration"].name == "foxglove.CameraCalibration"
        assert schema_of[f"/camera/{cam}/keypoints"].name == "foxglove.ImageAnnotations"
    assert schema_of["/tf"].name == "foxglove.FrameTransforms"
    assert schema_of["/robot/pose"].name == schema_of["/robot/goal"].name == "foxglove.PoseInFrame"
    assert schema_of["/pedestrians/scene"].name == "foxglove.SceneUpdate"
    assert schema_of["/map/occupancy"].name == "foxglove.Grid"
    for topic in ("/robot/state", "/pedestrians/state", "/perception/poses", "/episode/reward"):
        assert enc_of[topic] == "json" and schema_of[topic].encoding == "jsonschema"
        js = json.loads(schema_of[topic].data)
        payload = json.loads(msgs[(topic, 0)])
        assert js["type"] == "object" and set(js["required"]) == set(payload)

    # /tf: base_link -> camera_<cam> is T_base_cam (camera in OpenCV axes), world -> base_link is the odometry
    k = 7
    tfs = FrameTransforms()
    tfs.ParseFromString(msgs[("/tf", frames[k].t_ns)])
    by_child = {t.child_frame_id: t for t in tfs.transforms}
    x, y, yaw = frames[k].odom.astype(np.float64)
    wb = by_child["base_link"]
    assert wb.parent_frame_id == "world"
    assert (wb.translation.x, wb.translation.y) == pytest.approx((x, y))
    assert mcap_io.quat_to_rot(wb.rotation)[:2, :2] == pytest.approx(
        np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]), abs=1e-9)
    for cam in CAMERA_NAMES:
        tbc = np.asarray(meta.cameras[cam]["T_base_cam"])
        t = by_child[f"camera_{cam}"]
        assert t.parent_frame_id == "base_link"
        assert mcap_io.quat_to_rot(t.rotation) == pytest.approx(tbc[:3, :3], abs=1e-9)
        assert [t.translation.x, t.translation.y, t.translation.z] == pytest.approx(tbc[:3, 3])

    # 2D keypoints: every drawn point is a detected joint projected with K and T_base_cam, inside the image
    drawn = 0
    for fr in frames:
        for cam in CAMERA_NAMES:
            ann = ImageAnnotations()
            ann.ParseFromString(msgs[(TOPIC_KEYPOINTS_2D.format(cam=cam), fr.t_ns)])
            spec = meta.cameras[cam]
            kmat, tbc = np.asarray(spec["K"]), np.asarray(spec["T_base_cam"])
            pc = (fr.poses[fr.pose_mask].astype(np.float64) - tbc[:3, 3]) @ tbc[:3, :3]
            uv = pc[:, :2] / pc[:, 2:] * np.diag(kmat)[:2] + kmat[:2, 2]
            ok = (pc[:, 2] > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < spec["width"]) & (uv[:, 1] >= 0) & \
                 (uv[:, 1] < spec["height"])
            pts = np.array([(p.x, p.y) for pa in ann.points for p in pa.points]).reshape(-1, 2)
            assert len(pts) == ok.sum()
            if len(pts):
                assert np.allclose(np.sort(pts, axis=0), np.sort(uv[ok], axis=0))
            drawn += len(pts)
    assert drawn > 0
    # calibration on every frame, depth channel metadata says millimetres
    assert sum(1 for (t, _) in msgs if t == TOPIC_CALIB.format(cam="left")) == len(frames)
    assert summ.channels[next(c for c, ch in summ.channels.items()
                              if ch.topic == TOPIC_DEPTH.format(cam="left"))].metadata["unit"] == "mm"


def test_nonfinite_values_and_depth_quantisation(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    f0, f1 = frames[0], frames[1]
    vel = f1.ped_vel.copy()
    vel[0, 0] = np.nan
    depth = {c: d.copy() for c, d in f1.depth.items()}
    depth["left"][0, :4] = [1.0004999, 1.0005001, 70.0, -1.0]  # round down, round up, saturate, invalid
    f1 = replace(f1, d_o=float("inf"), ped_vel=vel, reward_terms={**f1.reward_terms, "near": float("-inf")},
                 depth=depth)
    with EpisodeWriter(tmp_path / "x.mcap", meta, occ) as w:
        w.add(f0)
        w.add(f1)
    got = list(read_episode(tmp_path / "x.mcap")[2])
    assert got[1].d_o == float("inf") and got[1].reward_terms["near"] == float("-inf")
    assert np.isnan(got[1].ped_vel[0, 0]) and np.array_equal(got[1].ped_vel[1:], vel[1:])
    assert got[1].depth["left"][0, :4].tolist() == pytest.approx([1.0, 1.001, 65.535, 0.0])
    assert_frames_equal(f0, got[0], depth_tol=DEPTH_TOL_M)


def test_float32_json_encoding_is_bit_exact() -> None:
    """9 significant digits identify every finite float32 (normals, subnormals, ±0, extremes) exactly."""
    rng = np.random.default_rng(0)
    bits = np.concatenate([rng.integers(0, 2**32, 200_000, dtype=np.uint64).astype(np.uint32),
                           np.array([0, 1, 0x007FFFFF, 0x00800000, 0x7F7FFFFF, 0x80000000, 0x3DCCCCCD], np.uint32)])
    x = bits.view(np.float32)
    x = x[np.isfinite(x)]
    back = mcap_io._dec_array(json.loads(mcap_io._enc_array(x)))
    assert back.dtype == np.float32 and np.array_equal(back.view(np.uint32), x.view(np.uint32))
    y = np.array([1.5, np.inf, -np.inf, np.nan, 1e-300], np.float64)
    z = mcap_io._dec_array(json.loads(mcap_io._enc_array(y)))
    assert z.dtype == np.float64 and np.array_equal(z, y, equal_nan=True)


def test_module_cli_recover_and_summary(recorded: Path, tmp_path: Path, capsys) -> None:
    part = tmp_path / "c.mcap.partial"
    part.write_bytes(recorded.read_bytes()[: chunk_layout(recorded)[3][0] + 5])
    assert mcap_io.main(["recover", str(part)]) == 0
    assert capsys.readouterr().out.strip() == f"recovered {count_frames(tmp_path / 'c.recovered.mcap')} frames " \
                                              f"into {tmp_path / 'c.recovered.mcap'}"
    assert mcap_io.main(["recover", str(part)]) == 2  # never overwrites
    assert "already exists" in capsys.readouterr().err
    assert mcap_io.main(["summary", str(recorded)]) == 0
    assert json.loads(capsys.readouterr().out)["n_frames"] == 21


# ------------------------------------------------------------------------------------------------ writer contract


def test_same_seed_identical_different_seed_differs(tmp_path: Path, recorded: Path) -> None:
    a = record_episode(tmp_path / "a.mcap", 1, CHUNK).final_path
    b = record_episode(tmp_path / "b.mcap", 1, CHUNK).final_path
    c = record_episode(tmp_path / "c.mcap", 2, CHUNK).final_path
    assert sha256(a) == sha256(b) == sha256(recorded)
    assert sha256(c) != sha256(a)


def test_lifecycle_partial_name_and_no_overwrite(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    final = tmp_path / "e.mcap"
    w = EpisodeWriter(final, meta, occ)
    assert not w.partial_path.exists()
    w.start()
    assert w.partial_path == tmp_path / "e.mcap.partial" and w.partial_path.exists() and not final.exists()
    for fr in frames:
        w.add(fr)
    with pytest.raises(ValueError, match="done=True"):
        w.add(replace(frames[-1], step=len(frames), t_ns=frames[-1].t_ns + 100_000_000))
    assert w.finish() == final and w.finish() == final  # idempotent
    assert final.exists() and not w.partial_path.exists() and w.frames_durable == len(frames)
    with pytest.raises(RuntimeError, match="finished"):
        w.add(frames[0])
    digest = sha256(final)
    with pytest.raises(OutputExistsError, match=re.escape(str(final))):
        EpisodeWriter(final, meta, occ).start()
    assert sha256(final) == digest
    stale = tmp_path / "s.mcap.partial"
    stale.write_bytes(b"left by a killed run")
    with pytest.raises(OutputExistsError, match="recover"):
        EpisodeWriter(tmp_path / "s.mcap", meta, occ).start()
    assert stale.read_bytes() == b"left by a killed run"


def test_add_checks_the_frame(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    with pytest.raises(ValueError, match="step expected 0, got 1"), EpisodeWriter(tmp_path / "f.mcap", meta, occ) as w:
        w.add(frames[1])
    bad = replace(frames[0], rgb={**frames[0].rgb, "left": frames[0].rgb["left"][:, :10]})
    with pytest.raises(ValueError, match=r"rgb\[left\] expected"), EpisodeWriter(tmp_path / "g.mcap", meta, occ) as w:
        w.add(bad)
    assert not (tmp_path / "g.mcap").exists() and (tmp_path / "g.mcap.partial").exists()


def test_exception_leaves_valid_partial(episode, tmp_path: Path) -> None:
    meta, occ, frames = episode
    final = tmp_path / "h.mcap"
    with pytest.raises(KeyError), EpisodeWriter(final, meta, occ, chunk_size=CHUNK) as w:
        for fr in frames[:5]:
            w.add(fr)
        raise KeyError("boom")
    assert not final.exists()
    partial = tmp_path / "h.mcap.partial"
    r = EpisodeReader(partial)  # closed cleanly: a valid MCAP with an 'aborted' record, not renamed
    assert r.n_frames == 5 and r.metadata["aborted"]["reason"] == "KeyError"
    out = recover(partial)
    assert out == tmp_path / "h.recovered.mcap" and count_frames(out) == 5 and partial.exists()
    for a, b in zip(frames[:5], read_episode(out)[2], strict=True):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    with pytest.raises(OutputExistsError, match="h.recovered.mcap"):
        recover(partial)


def test_missing_inputs_are_named(tmp_path: Path) -> None:
    p = tmp_path / "nope.mcap"
    for fn in (read_episode, count_frames, episode_summary, recover, EpisodeReader):
        with pytest.raises(InputMissingError, match=re.escape(str(p))):
            fn(p)


def test_graceful_signals_raise_interrupted_and_restore_handlers() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Interrupted) as ei, graceful_signals():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)  # the handler raises here
    assert ei.value.signum == signal.SIGTERM and ei.value.exit_code == 128 + signal.SIGTERM
    assert isinstance(ei.value, KeyboardInterrupt)
    assert signal.getsignal(signal.SIGTERM) is before
    # inside a critical section (what the writer uses around mcap calls) the signal waits for the section's end
    steps = []
    with pytest.raises(Interrupted), graceful_signals():
        with mcap_io._critical():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            steps.append("finished the write")
        steps.append("not reached")
    assert steps == ["finished the write"]


# ----------------------------------------------------------------------------------------- damaged / truncated files


def test_truncated_mcap_named_error_and_exact_salvage(episode, recorded: Path, tmp_path: Path) -> None:
    _, _, frames = episode
    size = recorded.stat().st_size
    chunks = chunk_layout(recorded)
    assert len(chunks) >= 4
    dt = frames[1].t_ns
    data = recorded.read_bytes()
    (s1, l1, _, _), (s2, l2, _, _) = chunks[1], chunks[2]
    cuts = [size - 1, size - 30, chunks[-1][0] + chunks[-1][1] + 5,  # footer / summary / message index gone
            s2 + l2 // 2, s2 + l2, s2 + 3, s1 + l1 // 3, chunks[0][0] + 10, 100]
    for cut in cuts:
        bad = tmp_path / f"cut{cut}.mcap"
        bad.write_bytes(data[:cut])
        for fn in (read_episode, count_frames, episode_summary, EpisodeReader):
            with pytest.raises(CorruptArtifactError) as ei:
                fn(bad)
            assert str(bad) in str(ei.value), (cut, str(ei.value))
        # salvage: exactly the frames of the chunks that lie completely before the cut
        n_expect = sum((t1 - t0) // dt + 1 for s, ln, t0, t1 in chunks if s + ln <= cut)
        partial = bad.rename(tmp_path / f"cut{cut}.mcap.partial")
        if n_expect == 0:
            with pytest.raises(CorruptArtifactError, match="nothing to salvage"):
                recover(partial)
            continue
        out = recover(partial)
        got = list(read_episode(out)[2])
        assert len(got) == n_expect, cut
        for a, b in zip(frames, got, strict=False):
            assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    # the raw library on the same kind of file fails with a bare, unnamed error: that is what we wrap
    with open(tmp_path / f"cut{s2 + 3}.mcap.partial", "rb") as f, pytest.raises(Exception) as raw:
        list(make_reader(f, validate_crcs=True).iter_messages())
    assert not isinstance(raw.value, CorruptArtifactError)


def test_recover_drops_a_trailing_incomplete_frame(episode, recorded: Path, tmp_path: Path) -> None:
    """A writer that cuts chunks inside frames (the plain mcap Writer): the frame split by the cut is dropped."""
    _, _, frames = episode
    dt = frames[1].t_ns
    split = tmp_path / "split.mcap"
    rewrite(recorded, split, chunk_size=45_000)
    chunks = chunk_layout(split)
    # a chunk whose last frame continues in the next chunk
    k = next(i for i in range(1, len(chunks) - 1) if chunks[i][3] == chunks[i + 1][2])
    start, length, _, t_end = chunks[k]
    part = tmp_path / "split.mcap.partial"
    part.write_bytes(split.read_bytes()[: start + length])
    out = recover(part)
    got = list(read_episode(out)[2])
    assert len(got) == t_end // dt  # frames 0 .. t_end/dt - 1; the frame at t_end is incomplete
    for a, b in zip(frames, got, strict=False):
        assert_frames_equal(a, b, depth_tol=DEPTH_TOL_M)
    assert EpisodeReader(out).metadata["recovery"]["incomplete_frames_dropped"] == "1"


def _flip(src: Path, dst: Path, offset: int) -> None:
    data = bytearray(src.read_bytes())
    data[offset] ^= 0x5A
    dst.write_bytes(bytes(data))


def _chunk_data_offset(path: Path, chunk_offset: int) -> tuple[int, int]:
    """(offset, length) of the compressed payload inside the chunk record at ``chunk_offset``."""
    b = path.read_bytes()
    p = chunk_offset + 9 + 8 + 8 + 8 + 4
    (n,) = np.frombuffer(b[p:p + 4], "<u4")
    p += 4 + int(n)
    (length,) = np.frombuffer(b[p:p + 8], "<u8")
    return p + 8, int(length)


@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_crc_flip_named_error(episode, tmp_path: Path, compression: str) -> None:
    meta, occ, frames = episode
    good = tmp_path / "good.mcap"
    with EpisodeWriter(good, meta, occ, chunk_size=CHUNK, compression=compression) as w:
        for fr in frames:
            w.add(fr)
    chunk_off = chunk_layout(good)[2][0]
    start, length = _chunk_data_offset(good, chunk_off)
    d = tmp_path / "damaged"
    d.mkdir()
    bad = d / "bad.mcap"
    _flip(good, bad, start + length // 2)
    with pytest.raises(CorruptArtifactError) as ei:
        read_episode(bad)
    msg = str(ei.value)
    assert str(bad) in msg and f"offset {chunk_off}" in msg and "chunk" in msg
    if compression == "none":
        assert "CRC mismatch" in msg
    with pytest.raises(CorruptArtifactError, match=re.escape(str(bad))):
        episode_summary(bad)
    # damage outside the chunks (in a message index record) is caught by the data-section CRC
    idx_bad = d / "idx.mcap"
    s0, l0, _, _ = chunk_layout(good)[0]
    _flip(good, idx_bad, s0 + l0 + 12)
    with pytest.raises(CorruptArtifactError, match="data section CRC mismatch"):
        read_episode(idx_bad)
    problems = check_mcap_dir(d)
    assert len(problems) == 2
    assert any(line.startswith(str(bad)) for line in problems)
    assert any(line.startswith(str(idx_bad)) for line in problems)
    # salvage keeps the chunks before the damaged one
    part = bad.rename(d / "bad.mcap.partial")
    dt = frames[1].t_ns
    n_expect = sum((t1 - t0) // dt + 1 for s, _, t0, t1 in chunk_layout(good) if s < chunk_off)
    assert count_frames(recover(part)) == n_expect


# -------------------------------------------------------------------------------------------- subprocess: signals


class _Proc:
    """The helper recorder in a subprocess, with its stdout lines read by a thread."""

    def __init__(self, out: Path, episodes: int = 3) -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "tests.recorder.helpers_mcap", str(out), "--episodes", str(episodes),
             "--frame-sleep", "0.03", "--chunk-size", str(CHUNK)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self.q: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.q.put(line.rstrip("\n"))
        self.q.put(None)

    def wait_for(self, pattern: str, timeout: float = 30.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.q.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                break
            if line is None:
                break
            self.lines.append(line)
            if m := re.search(pattern, line):
                return m
        self.p.kill()
        raise AssertionError(f"helper never printed {pattern!r}; output:\n" + "\n".join(self.lines))

    def rest(self) -> list[str]:
        while (line := self.q.get(timeout=10)) is not None:
            self.lines.append(line)
        return self.lines


def _finished_counts(lines: list[str]) -> dict[str, int]:
    return {f"ep{m[1]}.mcap": int(m[2]) for line in lines if (m := re.match(r"finished ep=(\d+) frames=(\d+)", line))}


def test_kill9_mid_episode(tmp_path: Path) -> None:
    out = tmp_path / "run"
    proc = _Proc(out)
    m = proc.wait_for(r"frame ep=2 step=12 durable=(\d+)")
    durable = int(m[1])
    proc.p.send_signal(signal.SIGKILL)
    assert proc.p.wait(timeout=10) == -signal.SIGKILL
    counts = _finished_counts(proc.rest())
    assert sorted(counts) == ["ep0.mcap", "ep1.mcap"]
    assert sorted(p.name for p in out.iterdir()) == ["ep0.mcap", "ep1.mcap", "ep2.mcap.partial"]
    for name, n in counts.items():  # finished episodes: CRC-checked, expected message count, same as a clean run
        r = EpisodeReader(out / name)
        assert r.n_frames == n and sum(r.message_counts.values()) == n * MSGS_PER_FRAME + 1
        assert sum(1 for _ in r.frames()) == n
        clean = record_episode(tmp_path / f"clean_{name}", int(name[2]), CHUNK).final_path
        assert sha256(out / name) == sha256(clean)
    partial = out / "ep2.mcap.partial"
    with pytest.raises(CorruptArtifactError, match=re.escape(str(partial))):
        read_episode(partial)
    problems = check_mcap_dir(out)
    assert len(problems) == 1 and problems[0].startswith(str(partial)) and "unfinished" in problems[0]
    rec = recover(partial)
    n = count_frames(rec)
    assert durable <= n <= 21 and durable >= 10
    clean = list(read_episode(record_episode(tmp_path / "clean_ep2.mcap", 2, CHUNK).final_path)[2])
    for a, b in zip(clean[:n], read_episode(rec)[2], strict=True):
        assert_frames_equal(a, b)
    assert "already recovered" in check_mcap_dir(out)[0]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_graceful(tmp_path: Path, sig: signal.Signals) -> None:
    out = tmp_path / "run"
    proc = _Proc(out)
    proc.wait_for(r"frame ep=1 step=6 ")
    t0 = time.monotonic()
    proc.p.send_signal(sig)
    rc = proc.p.wait(timeout=10)
    assert time.monotonic() - t0 < 5.0
    assert rc == 128 + sig
    lines = proc.rest()
    assert any(line.startswith(f"interrupted by {sig.name}") and "ep1.mcap.partial" in line for line in lines), lines
    assert sorted(p.name for p in out.iterdir()) == ["ep0.mcap", "ep1.mcap.partial"]
    assert EpisodeReader(out / "ep0.mcap").n_frames == _finished_counts(lines)["ep0.mcap"]
    # the interrupted episode was closed cleanly: a valid MCAP holding every frame added before the signal
    partial = EpisodeReader(out / "ep1.mcap.partial")
    last = max(int(m[1]) for line in lines if (m := re.match(r"frame ep=1 step=(\d+)", line)))
    assert partial.n_frames == last + 1 and partial.metadata["aborted"]["reason"] == "Interrupted"
    assert count_frames(recover(out / "ep1.mcap.partial")) == last + 1


def test_recover_copies_payloads_byte_for_byte(recorded: Path, tmp_path: Path) -> None:
    part = tmp_path / "r.mcap.partial"
    shutil.copy(recorded, part)
    out = recover(part)
    with open(recorded, "rb") as f1, open(out, "rb") as f2:
        a = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f1).iter_messages()]
        b = [(ch.topic, m.log_time, m.data) for _, ch, m in make_reader(f2).iter_messages()]
    assert a == b
    assert EpisodeReader(out).metadata["recovery"]["frames_salvaged"] == str(count_frames(recorded))

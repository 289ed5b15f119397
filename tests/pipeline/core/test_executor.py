"""pipeline.core.executor: the local pool and Ray give the rows of a serial run, in job order; a real local Ray
cluster (a head and one more node on this machine) records and evaluates byte- and row-identically to the local
pool, survives a worker killed mid-episode, and refuses what it cannot use with one named error."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.core.config import load_config
from pipeline.core.errors import ConfigError, CorruptArtifactError
from pipeline.core.executor import (
    BUNDLE_KEEP_S,
    Bundle,
    Executor,
    check_executor,
    check_ray_files,
    map_jobs,
    ray_session,
    receive_file,
    resolve_executor,
    returned_files,
)

SCENE_ARGS = ["--scenes", "hallway", "--densities", "0.05", "--sim.camera.width-px", "64",
              "--sim.camera.height-px", "48"]
RECORD = [*SCENE_ARGS, "--episodes", "4", "--sim.max-episode-s", "4.0"]
NAMES = [f"hallway_d0.05_s{k}.mcap" for k in range(4)]


def _square_and_pid(k: int) -> tuple[int, int]:
    return k * k, os.getpid()


def test_pool_and_serial_give_the_same_rows_in_job_order():
    jobs = list(range(7))
    seen: list[int] = []
    serial = map_jobs(_square_and_pid, jobs, workers=1, desc="serial", progress=False)
    pooled = map_jobs(_square_and_pid, jobs, workers=2, desc="pool", progress=False,
                      on_result=lambda i, r: seen.append(i))
    assert [r for r, _ in serial] == [r for r, _ in pooled] == [k * k for k in jobs]
    assert {p for _, p in serial} == {os.getpid()}
    assert os.getpid() not in {p for _, p in pooled}
    assert sorted(seen) == jobs


def test_executor_choice(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert resolve_executor("auto") == "local" and resolve_executor("ray") == "ray"
    assert resolve_executor("auto", "10.0.0.1:6379") == "ray"
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert resolve_executor("auto") == "ray" and resolve_executor("local") == "local"
    with pytest.raises(ConfigError, match="record.executor: expected one of"):
        check_executor("dask", "", "record")
    with pytest.raises(ConfigError, match="ray_address"):
        check_executor("local", "10.0.0.1:6379", "eval")
    from rl.stage import TrainConfig

    with pytest.raises(ConfigError, match=r"train.ray_files: expected one of \['shared', 'transfer'\], got 'nfs'"):
        load_config(TrainConfig, "train", "smoke", {"ray_files": "nfs"})


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_address_nobody_answers_is_one_named_error_in_seconds(tmp_path):
    t = time.monotonic()
    with pytest.raises(ConfigError, match="nobody answers"), ray_session(f"127.0.0.1:{_free_port()}", tmp_path, 1):
        pass
    assert time.monotonic() - t < 30  # ray.init alone keeps retrying for minutes
    with pytest.raises(ConfigError, match="expected host:port"), ray_session("no-port-here", tmp_path, 1):
        pass


def test_cli_unreachable_ray_address_exits_2_and_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{_free_port()}")
    data = tmp_path / "data"
    rc = cli.main(["record", "--data-dir", str(data), *RECORD])
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert rc == 2 and len(err) == 1 and "nobody answers" in err[0]
    assert not (data / "raw" / "expert").exists() or not any((data / "raw" / "expert").glob("*.mcap"))


def test_a_transferred_file_is_written_only_when_its_bytes_match(tmp_path):
    """receive_file (``ray_files: transfer``): the bytes a task returned land atomically when their sha256 is the
    one the task computed; a mismatch is one named error and leaves no file (nor a temporary one) behind."""
    data = b"an episode"
    path = receive_file(tmp_path / "raw" / "a.mcap", data, hashlib.sha256(data).hexdigest())
    assert path.read_bytes() == data
    with pytest.raises(CorruptArtifactError, match=r"b\.mcap: the 9 bytes a Ray task returned have sha256"):
        receive_file(tmp_path / "raw" / "b.mcap", data[:-1], hashlib.sha256(data).hexdigest())
    assert sorted(p.name for p in (tmp_path / "raw").iterdir()) == ["a.mcap"]
    with pytest.raises(ConfigError, match=r"record.ray_files: expected one of \['shared', 'transfer'\], got 'nfs'"):
        check_ray_files("nfs", "record")
    local = Executor.of(type("C", (), {"executor": "local", "ray_address": "", "data_dir": ".",
                                       "ray_files": "transfer"})())
    assert local.files == "transfer" and not local.transfers  # only Ray tasks transfer their files
    assert Executor("ray", "", Path("."), "transfer").transfers and not Executor("ray", "", Path(".")).transfers


def test_a_bundle_unpacks_once_per_node_where_its_paths_say(tmp_path, monkeypatch):
    """Bundle (``ray_files: transfer``): files under their deepest common folder, a key over names and bytes, unpacked
    into one folder per bundle (a second unpack reuses it; no temporary folder left; bundles unused for a day are
    removed); returned_files lists a scratch folder's files with their sha256."""
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path / "node"))
    (tmp_path / "node").mkdir()
    a, b = tmp_path / "ckpt" / "policy" / "full" / "policy.json", tmp_path / "ckpt" / "bev" / "encoder.bin"
    bundle = Bundle.of({a: b"{}", b: b"\x00\x01"})
    assert bundle.root == str(tmp_path / "ckpt") and [n for n, _ in bundle.files] == ["bev/encoder.bin",
                                                                                      "policy/full/policy.json"]
    assert bundle.key == Bundle.of({b: b"\x00\x01", a: b"{}"}).key != Bundle.of({a: b"{ }", b: b"\x00\x01"}).key
    root = bundle.unpack()
    assert bundle.local(root, a).read_bytes() == b"{}" and bundle.local(root, b.parent) == root / "bev"
    (root / "marker").write_text("kept")
    assert bundle.unpack() == root and (root / "marker").is_file()  # once per node
    assert [p.name for p in (tmp_path / "node").iterdir()] == [root.name]
    assert [(n, d) for n, d, _ in returned_files(root)] == [("bev/encoder.bin", b"\x00\x01"), ("marker", b"kept"),
                                                            ("policy/full/policy.json", b"{}")]
    assert all(h == hashlib.sha256(d).hexdigest() for _, d, h in returned_files(root))
    # a task killed while unpacking left its temporary folder: removed by the next unpack on the node, while a live
    # process's is kept
    dead = subprocess.Popen(["true"])
    dead.wait()
    other = Bundle.of({a: b"{}"})
    name = f"icrowdnav-files-{other.key[:20]}"
    (tmp_path / "node" / f".{name}-{dead.pid}-x1").mkdir()
    (tmp_path / "node" / f".{name}-{os.getpid()}-x2").mkdir()
    assert other.unpack().name == name
    assert sorted(p.name for p in (tmp_path / "node").iterdir()) == sorted([root.name, name,
                                                                           f".{name}-{os.getpid()}-x2"])
    # bundles no task used for BUNDLE_KEEP_S are removed when a new one is unpacked; using one marks it used
    stale = time.time() - BUNDLE_KEEP_S - 60
    os.utime(root, (stale, stale))
    os.utime(tmp_path / "node" / name, (stale, stale))
    assert other.unpack().name == name  # used again: kept, and no longer stale
    third = Bundle.of({b: b"\x02"}).unpack()
    assert sorted(p.name for p in (tmp_path / "node").iterdir()) == sorted([name, third.name,
                                                                           f".{name}-{os.getpid()}-x2"])


def _pair_with(k: int, shared: int) -> tuple[int, int]:
    return k, shared


def test_a_shared_value_reaches_every_job():
    assert map_jobs(_pair_with, [1, 2, 3], 2, "t", progress=False, shared=7) == [(1, 7), (2, 7), (3, 7)]


# ------------------------------------------------------------------------------------------ a real Ray cluster
def _digests(d: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.glob("*.mcap"))}


def _rows(d: Path) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k not in ("seconds", "mcap_seconds")}
            for line in (d / "episodes.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def local_record(tmp_path_factory) -> Path:
    """The reference: the same recording with the local pool."""
    data = tmp_path_factory.mktemp("local") / "data"
    assert cli.main(["record", "--data-dir", str(data), *RECORD, "--workers", "2", "--executor", "local"]) == 0
    return data / "raw" / "expert"


@pytest.fixture(scope="module")
def cluster():
    """A Ray head and a second node process on this machine (one CPU each); RAY_ADDRESS points at it."""
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    for attempt in range(2):  # Ray gives a raylet 30 s to register (hard-coded): a loaded machine can miss it once
        c = Cluster(initialize_head=False)
        try:
            c.add_node(num_cpus=1, include_dashboard=False)
            c.add_node(num_cpus=1)
            c.wait_for_nodes()
            break
        except Exception:
            c.shutdown()
            if attempt:
                raise
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_ADDRESS", c.address)
        yield c
    if ray.is_initialized():
        ray.shutdown()
    c.shutdown()


@pytest.mark.slow
def test_record_and_eval_on_ray_equal_the_local_pool(cluster, local_record, tmp_path):
    data = tmp_path / "data"
    assert cli.main(["record", "--data-dir", str(data), *RECORD, "--workers", "2"]) == 0  # auto: RAY_ADDRESS
    out = data / "raw" / "expert"
    assert list(_digests(out)) == NAMES and _digests(out) == _digests(local_record)
    assert _rows(out) == _rows(local_record)

    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run
    from sim.env import SimConfig

    tiny = SimConfig(max_episode_s=3.0)
    base = EvalConfig(methods=["expert"], scenes=["office_lobby"], densities=[0.1], goals=2, trials=1,
                      routing_scenes=[], scenarios=[], workers=2, figures=1, videos=0, sim=tiny, progress=False)
    base.long_horizon = replace(base.long_horizon, runs=0)
    rows = {}
    for ex in ("ray", "local"):
        run(replace(base, data_dir=str(tmp_path / ex), executor=ex))
        d = tmp_path / ex / "eval" / "benchmark"
        rows[ex] = (d / "episodes.jsonl").read_text()
        assert len(list((d / "figures").glob("office_lobby_*.png"))) == 1  # a file a task wrote reaches the data dir
    assert rows["ray"] == rows["local"]


def _untrained_teacher(data: Path) -> Path:
    """A lookahead teacher with its initial weights as ``train`` would leave it in ``data`` (manifest stub)."""
    import torch

    from rl.policy import build_policy, describe, save_policy
    from rl.teacher import teacher_net
    from sim.env import CrowdNavEnv, SimConfig

    torch.manual_seed(0)  # the same weights in every data dir
    sim = SimConfig()
    env = CrowdNavEnv(config=replace(sim, scene="office_lobby", obs_mode="privileged", action_type="discrete"))
    net = teacher_net({"encoder": "lookahead"}, sim)
    out = data / "checkpoints" / "policy" / "teacher"
    save_policy(out, build_policy("teacher", None, env.observation_space, net),
                describe("teacher", None, env.observation_space, net))
    (out / "manifest.json").write_text("{}")
    env.close()
    return out


@pytest.mark.slow
def test_eval_with_files_through_the_object_store_equals_the_local_pool(cluster, tmp_path):
    """``eval --ray_files transfer``: the teacher's checkpoint travels to the nodes as one bundle, each episode's
    figure and trace come back through the object store; the rows equal the local pool's, the files arrive, and the
    data dir holds no temporary file."""
    from evaluation.stage import EvalConfig
    from pipeline.verbs.eval import run
    from rl.policy import checkpoint_bundle
    from sim.env import SimConfig

    base = EvalConfig(methods=["expert", "teacher"], scenes=["office_lobby"], densities=[0.1], goals=2, trials=1,
                      routing_scenes=[], scenarios=[], workers=2, figures=1, videos=0,
                      sim=SimConfig(max_episode_s=3.0), progress=False, paired_with="teacher")
    base.long_horizon = replace(base.long_horizon, runs=0)
    got, ckpts = {}, {}
    for ex, files in (("ray", "transfer"), ("local", "shared")):
        ckpts[ex] = _untrained_teacher(tmp_path / ex)
        run(replace(base, data_dir=str(tmp_path / ex), executor=ex, ray_files=files))
        d = tmp_path / ex / "eval" / "benchmark"
        got[ex] = ((d / "episodes.jsonl").read_text(),
                   sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.suffix in (".png", ".npz")))
        assert not [p for p in d.rglob("*") if p.name.startswith(".") or p.suffix in (".tmp", ".partial")]
    assert got["ray"] == got["local"]
    assert [f for f in got["ray"][1] if "_s2000" in f] == [  # a figure per method, a trace per episode
        *(f"figures/office_lobby_d0.1_s20000_{m}.png" for m in ("expert", "teacher")),
        *(f"traces/office_lobby_d0.1_s{s}_{m}.npz" for s in (20000, 20001) for m in ("expert", "teacher"))]
    unpacked = Path(tempfile.gettempdir()) / f"icrowdnav-files-{checkpoint_bundle([ckpts['ray']]).key[:20]}"
    assert (unpacked / "policy.safetensors").is_file()  # what the nodes acted from (the bundle root: its folder)
    shutil.rmtree(unpacked)


_KILLER = """
import glob, os, signal, sys, time
import psutil
task, ready, child, wait = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
deadline = time.monotonic() + 120
while time.monotonic() < deadline:
    pids = [p for p in psutil.process_iter(["pid", "cmdline"])
            if f"ray::{task}" in " ".join(p.info.get("cmdline") or [])]
    if child:  # only the worker whose child process runs `child`
        try:
            pids = [p for p in pids if any(child in " ".join(c.cmdline()) for c in p.children())]
        except psutil.Error:
            pids = []
    if pids and (not ready or glob.glob(ready)):
        time.sleep(wait)
        os.kill(pids[0].pid, signal.SIGKILL)
        print(pids[0].pid, flush=True)
        break
    time.sleep(0.02)
"""


def _start_killer(task: str, ready: str = "", wait_s: float = 0.0, child: str = "") -> subprocess.Popen:
    """A separate process that SIGKILLs the first Ray worker seen running ``task`` (with a child process whose
    command line holds ``child``, when given; once the glob ``ready`` matches a file, when given), ``wait_s`` after
    seeing it, and prints its pid. A process, not a thread of the test: the driver's own work holds the GIL and
    could starve a polling thread past a short task."""
    return subprocess.Popen([sys.executable, "-c", _KILLER, task, ready, child, str(wait_s)],
                            stdout=subprocess.PIPE, text=True)


def _killed(killer: subprocess.Popen) -> list[int]:
    try:
        out, _ = killer.communicate(timeout=5)
    except subprocess.TimeoutExpired:
        killer.kill()
        out, _ = killer.communicate()
    return [int(v) for v in out.split()]


@pytest.mark.slow
def test_a_worker_killed_mid_episode_loses_and_duplicates_nothing(cluster, local_record, tmp_path):
    data = tmp_path / "data"
    out = data / "raw" / "expert"
    killer = _start_killer("_record_task", f"{out}/*.mcap.partial")  # a worker recording (.partial open)
    assert cli.main(["record", "--data-dir", str(data), *RECORD, "--workers", "2", "--executor", "ray"]) == 0
    assert _killed(killer), "no worker was seen recording"
    assert _digests(out) == _digests(local_record)  # every episode, once, byte-identical
    assert not list(out.glob("*.partial")) and [r["file"] for r in _rows(out)] == NAMES


@pytest.mark.slow
def test_files_through_the_object_store_equal_the_local_pool_and_survive_a_killed_worker(cluster, local_record,
                                                                                         tmp_path):
    """``--ray_files transfer``: the tasks get no data-dir path (they record into a scratch folder of their node and
    return the bytes); a worker SIGKILLed mid-episode is retried; every episode arrives once, byte-identical to the
    local pool's, with the same rows, and no temporary file is left in the data dir."""
    data = tmp_path / "data"
    out = data / "raw" / "expert"
    killer = _start_killer("_record_transfer_task", wait_s=0.3)  # the first transfer task, once it has started
    assert cli.main(["record", "--data-dir", str(data), *RECORD, "--workers", "2", "--executor", "ray",
                     "--ray_files", "transfer"]) == 0
    assert _killed(killer), "no worker was seen recording"
    assert _digests(out) == _digests(local_record)
    assert _rows(out) == _rows(local_record)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".") or p.suffix in (".partial", ".tmp")]


@pytest.mark.slow
def test_without_an_address_a_run_starts_its_own_instance_beside_another_cluster(cluster, tmp_path, monkeypatch):
    """No address given: the run's own Ray instance with its worker count, even while another cluster runs on this
    machine (here the fixture's, recorded in /tmp/ray/ray_current_cluster as `ray start` and every test cluster
    record theirs) — a bare ``ray.init()`` joined that one and refused the worker count, which failed a run whenever
    two ran at once on one machine."""
    import ray

    from pipeline.core.executor import ray_session

    monkeypatch.delenv("RAY_ADDRESS")
    with ray_session("", tmp_path, 1):
        assert ray.cluster_resources()["CPU"] == 1.0 and len(ray.nodes()) == 1  # the cluster has two 1-CPU nodes
    assert not ray.is_initialized()


@pytest.mark.slow
def test_a_data_dir_the_nodes_cannot_reach_is_one_named_error(cluster, tmp_path):
    import ray

    from pipeline.core.executor import check_data_dir

    ray.init(address=cluster.address, log_to_driver=False)
    try:
        with pytest.raises(ConfigError, match=r"the Ray workers cannot reach it — on node .* does not exist"):
            check_data_dir(tmp_path / "only_on_the_driver")
        check_data_dir(tmp_path)
    finally:
        ray.shutdown()
    assert Executor().kind == "local"


@pytest.mark.slow
def test_train_all_runs_each_variant_in_a_ray_task_and_reruns_a_killed_one(cluster, tmp_path):
    """``train-all`` on the cluster: the teacher, then the other variants, each in a Ray task (the stand-in
    ``train``'s parent is a Ray worker); a task whose worker is killed mid-variant is rerun with ``--resume`` and
    its variant finishes once."""
    from pipeline.verbs.train_all import make_plan, run_plan
    from tests.pipeline.test_train_all import STANDIN, runs, standin

    data = tmp_path / "data"
    standin(data, seconds=4.0)
    # SIGKILL the Ray worker running sarl_om's task once its stand-in has started
    killer = _start_killer("run_child", f"{data}/checkpoints/policy/sarl_om/runs.txt", child="sarl_om")
    plan = make_plan(["--variants", "[sarl_om, teacher, vint]", "--data-dir", str(data), "--cpus_per_variant", "1"])
    assert plan.executor == "ray"  # auto: RAY_ADDRESS
    res = run_plan(plan, module=STANDIN)
    killed = _killed(killer)
    assert [(r["name"], r["returncode"]) for r in res] == [("teacher", 0), ("sarl_om", 0), ("vint", 0)]
    assert killed, "no Ray worker was seen running sarl_om"
    assert [len(runs(data, v)) for v in ("teacher", "sarl_om", "vint")] == [1, 2, 1]
    assert all(parent.startswith("ray::") for v in ("teacher", "vint") for _, parent, _ in runs(data, v))
    assert all("--resume" in argv for _, _, argv in runs(data, "sarl_om"))
    assert (data / "checkpoints" / "policy" / "sarl_om" / "done").is_file()

"""`proxycodec batch`: one command over many scenes (``proxycodec.batch``), one after another here or on Ray (a
local Ray, and a two-node cluster on this machine): outputs byte-identical to the command run alone, a bad input
failing alone with its one-line error, re-runs skipping what finished."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from click.testing import CliRunner
from test_codec import tiny_model

from proxycodec.batch import plan, run_batch
from proxycodec.cli.batch import split_args
from proxycodec.cli.main import cli
from proxycodec.errors import ProxycodecError

#: encode options small enough for a test (each task is a child process: ~3 s, most of it importing torch)
OPTIONS = ["--no-distill", "--predictor-iters", "15", "--entropy", "zstd", "--zstd-level", "3"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("scenes")
    paths = []
    for i in range(3):
        ply, _ = tiny_model(120 + 20 * i, seed=i).save(d / f"s{i}.ply")
        paths.append(str(ply))
    bad = d / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")  # no end_header
    return paths, str(bad)


def _alone(scene: str, out: str) -> bytes:
    """The command run by hand, as the batch's tasks run it (one thread)."""
    r = subprocess.run([sys.executable, "-m", "proxycodec.cli", "--threads", "1", "encode", scene, "-o", out, *OPTIONS],
                       capture_output=True, text=True, env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert r.returncode == 0, r.stderr
    with open(out, "rb") as fh:
        return fh.read()


def _outputs(records) -> dict[str, bytes]:
    out = {}
    for r in records:
        if r["status"] in ("ok", "skipped"):
            with open(r["output"], "rb") as fh:
                out[r["name"]] = fh.read()
    return out


# ------------------------------------------------------------------------------------------------ planning
def test_the_commands_options_pass_through_and_inputs_are_what_is_left():
    enc = cli.commands["encode"]
    inputs, opts = split_args(enc, ["a.ply", "--no-distill", "b.ply", "--distill-iters", "5", "--seed=3", "c"])
    assert inputs == ["a.ply", "b.ply", "c"] and opts == ["--no-distill", "--distill-iters", "5", "--seed=3"]
    with pytest.raises(ProxycodecError, match="has no option --bogus"):
        split_args(enc, ["a.ply", "--bogus"])
    with pytest.raises(ProxycodecError, match="needs a value"):
        split_args(enc, ["a.ply", "--seed"])


def test_tasks_are_named_after_their_inputs_and_keyed_by_input_bytes_and_options(tmp_path):
    a, b = tmp_path / "x" / "s.ply", tmp_path / "y" / "s.ply"
    for p in (a, b):
        p.parent.mkdir()
        p.write_bytes(b"one")
    t = plan("encode", [str(a), str(b)], tmp_path / "out", ["--seed", "1"])
    assert [x.name for x in t] == ["s", "s_2"] and t[1].output.endswith("s_2.pxc")
    assert t[0].argv[:4] == ("encode", str(a), "-o", str(tmp_path / "out" / "s.pxc")) and "--json" in t[0].argv
    assert t[0].key == t[1].key  # the same bytes and options
    b.write_bytes(b"two")
    assert plan("encode", [str(b)], tmp_path / "out", ["--seed", "1"])[0].key != t[1].key
    assert plan("encode", [str(a)], tmp_path / "out", ["--seed", "2"])[0].key != t[0].key
    (a.parent / "s.weights.pxc").write_bytes(b"w")  # a PLY's sidecar is part of its input
    assert plan("encode", [str(a)], tmp_path / "out", ["--seed", "1"])[0].key != t[0].key
    ev = plan("eval", [str(a)], tmp_path / "out", [], dataset=str(tmp_path))[0]
    assert ev.argv[:5] == ("eval", str(a), str(tmp_path), "-o", str(tmp_path / "out" / "s_eval"))
    for bad, match in ((dict(command="encode", options=["-o", "x"]), "names every output"),
                       (dict(command="eval", options=[]), "--dataset"),
                       (dict(command="decode", options=[]), "not 'decode'")):
        with pytest.raises(ProxycodecError, match=match):
            plan(bad["command"], [str(a)], tmp_path / "out", bad["options"])


# ------------------------------------------------------------------------------------------------ running
def test_a_batch_writes_what_each_command_writes_alone_and_a_bad_input_fails_alone(scenes, tmp_path):
    good, bad = scenes
    tasks = plan("encode", [good[0], bad, good[1]], tmp_path / "out", OPTIONS, threads=1)
    said = []
    records, how = run_batch(tasks, use_ray=False, say=said.append)
    assert how["engine"] == "sequential" and how["ran"] == 3
    assert [r["status"] for r in records] == ["ok", "error", "ok"]
    assert records[1]["error"].startswith(f"{bad}: ") and "end_header" in records[1]["error"]
    assert "\n" not in records[1]["error"] and "Traceback" not in records[1]["error"]
    assert len(said) == 3 and said[-1].startswith("batch [####################] 3/3  failed 1")
    for r in (records[0], records[2]):
        assert r["bytes"] > 0 and r["peak_rss_mb"] > 50 and r["seconds"] > 0
    got = _outputs(records)
    assert got["s0"] == _alone(good[0], str(tmp_path / "alone0.pxc"))
    assert got["s1"] == _alone(good[1], str(tmp_path / "alone1.pxc"))
    # a re-run skips what finished (same input and options) and runs the failed one again
    again, how = run_batch(plan("encode", [good[0], bad, good[1]], tmp_path / "out", OPTIONS, threads=1),
                           use_ray=False, say=lambda s: None)
    assert [r["status"] for r in again] == ["skipped", "error", "skipped"] and how["ran"] == 1
    # another option is another task
    other, _ = run_batch(plan("encode", [good[0]], tmp_path / "out", OPTIONS + ["--seed", "4"], threads=1),
                         use_ray=False, say=lambda s: None)
    assert other[0]["status"] == "ok"


#: fit options small enough for a test
FIT = ["--init-points", "300", "--no-proxies", "--max-width", "24", "--checkpoint-every", "0"]


def _stop_a_batch_fit(tmp_path, *engine: str):
    """Start `batch fit` on a tiny dataset (``engine``: --no-ray or --ray), SIGTERM the batch once its fit trains:
    (dataset, out dir, the task's log, the iteration its checkpoint holds). The batch and its fit exit 143, the fit
    after writing its checkpoint."""
    import signal
    import time

    from conftest import signal_when_ready, write_corner_dataset

    ds = write_corner_dataset(tmp_path / "ds", 32)
    out = tmp_path / "d"
    # started with SIGINT ignored, as every child of a background job is (`.ci/run &`): Ray's cancel must work there too
    p = subprocess.Popen([sys.executable, "-m", "proxycodec.cli", "batch", "fit", str(ds), "--out", str(out), *engine,
                          "--cpus-per-task", "1", *FIT, "--iters", "1000000"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    log = out / "logs" / "ds.log"

    def training():
        deadline = time.monotonic() + 240
        while not (log.exists() and any(ln.startswith("it ") for ln in log.read_text().splitlines())):
            assert time.monotonic() < deadline and p.poll() is None, "the fit never started training"
            time.sleep(0.1)

    _, err = signal_when_ready(p, signal.SIGTERM, training, timeout=240)
    assert p.returncode == 143 and err.splitlines()[-1] == "terminated (SIGTERM)", err
    child = log.read_text().splitlines()
    assert child[-1] in ("terminated (SIGTERM)", "interrupted") and \
        child[-2].startswith("checkpoint saved at iteration "), child[-3:]
    assert (out / "ds.ckpt.pxc").exists() and not (out / "ds.ply").exists()
    return ds, out, log, int(child[-2].split()[4].rstrip(":"))


def test_a_stopped_batch_stops_its_training_child_and_the_next_run_resumes_it(tmp_path):
    """SIGTERM to the batch reaches its running `fit` (which writes its checkpoint, then exits 143 as the batch does);
    the next run of the batch continues that fit (--resume), and a checkpoint of other options is started afresh."""
    import shutil

    ds, out, log, saved = _stop_a_batch_fit(tmp_path, "--no-ray")
    assert log.read_text().splitlines()[-1] == "terminated (SIGTERM)"
    ckpt = out / "ds.ckpt.pxc"
    fit = FIT
    shutil.copy(ckpt, tmp_path / "kept.ckpt.pxc")

    recs, _ = run_batch(plan("fit", [str(ds)], out, [*fit, "--iters", str(saved + 2)], threads=1), use_ray=False,
                        say=lambda s: None)
    text = log.read_text()
    assert recs[0]["status"] == "ok" and recs[0]["resumed"] and recs[0]["attempts"] == 1, recs[0]
    assert f"at iteration {saved}" in text and f"done: {saved + 2} iterations" in text, text
    assert (out / "ds.ply").exists() and not ckpt.exists()

    shutil.copy(tmp_path / "kept.ckpt.pxc", ckpt)  # a checkpoint of other options (the seed): started afresh
    recs, _ = run_batch(plan("fit", [str(ds)], out, [*fit, "--iters", "3", "--seed", "5"], threads=1), use_ray=False,
                        say=lambda s: None)
    text = log.read_text()
    assert recs[0]["status"] == "ok" and not recs[0]["resumed"] and recs[0]["attempts"] == 1, recs[0]
    assert "resumed" not in text and "done: 3 iterations" in text, text
    assert not ckpt.exists()


def test_cli_batch_summarises_and_exits_1_when_a_scene_failed(scenes, tmp_path):
    good, bad = scenes
    r = CliRunner().invoke(cli, ["batch", "encode", good[2], bad, "--out", str(tmp_path / "d"), "--no-ray",
                                 "--cpus-per-task", "1", *OPTIONS])
    assert r.exit_code == 1, r.output
    assert "| s2.ply | ok | s2.pxc |" in r.stdout.replace(good[2], "s2.ply")
    summary = json.loads((tmp_path / "d" / "batch.json").read_text())
    assert [t["status"] for t in summary["tasks"]] == ["ok", "error"]
    assert (tmp_path / "d" / "logs" / "bad.log").read_text().strip().startswith("error: ")
    assert (tmp_path / "d" / "batch.md").read_text().startswith("# proxycodec batch: 2 tasks")
    r = CliRunner().invoke(cli, ["batch", "encode", good[2], "--out", str(tmp_path / "e"), "--no-ray", "-o", "x"])
    assert r.exit_code == 2 and "names every output" in r.output
    r = CliRunner().invoke(cli, ["batch", "encode", "--out", str(tmp_path / "e")])
    assert r.exit_code == 2 and "no inputs" in r.output


# ------------------------------------------------------------------------------------------------ Ray
@pytest.fixture()
def ray():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e \".[ray]\")")
    yield ray
    if ray.is_initialized():
        ray.shutdown()


def test_on_a_local_ray_the_outputs_are_those_of_the_sequential_run(ray, scenes, tmp_path):
    good, bad = scenes
    seq, _ = run_batch(plan("encode", good, tmp_path / "seq", OPTIONS, threads=1), use_ray=False,
                       say=lambda s: None)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    records, how = run_batch(plan("encode", good + [bad], tmp_path / "ray", OPTIONS, threads=1), use_ray=True,
                             cpus_per_task=1, say=lambda s: None)
    assert how["engine"] == "ray" and how["cluster_cpus"] == 2
    assert [r["status"] for r in records] == ["ok", "ok", "ok", "error"]
    assert _outputs(records) == _outputs(seq)


def test_a_stopped_batch_on_ray_stops_its_training_child(ray, tmp_path):
    """On Ray too: SIGTERM to the batch cancels its task, which stops its `fit` child so that it writes its checkpoint
    (Ray raises KeyboardInterrupt in the task, whose wait for its child is polled so that it can, and the task sends
    the child SIGTERM 5 s on)."""
    _stop_a_batch_fit(tmp_path, "--ray")


def test_a_two_node_cluster_runs_the_same_batch(ray, scenes, tmp_path):
    from ray.cluster_utils import Cluster

    good, _ = scenes
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        ray.init(address=cluster.address, log_to_driver=False)
        records, how = run_batch(plan("encode", good, tmp_path / "two", OPTIONS, threads=1), use_ray=True,
                                 cpus_per_task=1, say=lambda s: None)
        assert how["nodes"] == 2 and how["cluster_cpus"] == 2
        assert [r["status"] for r in records] == ["ok"] * 3
        seq, _ = run_batch(plan("encode", good, tmp_path / "seq", OPTIONS, threads=1), use_ray=False,
                           say=lambda s: None)
        assert _outputs(records) == _outputs(seq)
    finally:
        ray.shutdown()
        cluster.shutdown()

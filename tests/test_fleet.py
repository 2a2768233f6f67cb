"""aqfg fleet: the manifest, the joint fits on a two-process Dask LocalCluster (equal to the
single-process joint fit), a worker killed mid-run, and the outputs."""
from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
from conftest import data_path

from aqfg.cli import main
from aqfg.commands.common import EXIT_DATA
from aqfg.data.io import load_mission, load_truth, save_mission
from aqfg.data.mission import with_gnss_every
from aqfg.fg.batch import BatchSmoother
from aqfg.fg.settings import FGSettings
from aqfg.fg.fit import fit_fg
from aqfg.fleet import ManifestError, fit_fleet, load_manifest, write_manifest
from aqfg.fleet.report import differs_from_fleet, effect_document, save_fleet
from aqfg.outputs import dumps
from aqfg.result import BaseFit, EffectStep, FleetEffect
from aqfg.sim import simulate, true_params

distributed = pytest.importorskip("distributed")


# ---------------------------------------------------------------- manifest
def _mission_dir(root, name):
    d = root / name
    d.mkdir(parents=True)
    (d / "mission.toml").write_text('format = "aqfg-mission/1"\n')
    return d


def _manifest(root, text):
    p = root / "fleet.toml"
    p.write_text(text)
    return p


def test_manifest_reads_vehicles_and_relative_paths(tmp_path):
    _mission_dir(tmp_path, "runs/a")
    _mission_dir(tmp_path, "runs/b")
    p = _manifest(tmp_path, '[[vehicle]]\nname = "otter-1"\nmissions = ["runs/a"]\n'
                            '[[vehicle]]\nname = "otter-2"\nmissions = ["runs/b"]\n')
    man = load_manifest(p)
    assert [v.name for v in man.vehicles] == ["otter-1", "otter-2"]
    assert man.vehicles[1].missions[0].path == tmp_path / "runs" / "b"
    assert man.n_missions == 2


def test_manifest_takes_absolute_paths_and_globs(tmp_path):
    store = tmp_path / "store"                   # shared storage, outside the manifest's folder
    for d in ("2026-06-01a", "2026-06-01b", "2026-07-01a"):
        _mission_dir(store, d)
    (store / "2026-06-notes").mkdir()            # matched by the glob, not a mission: skipped
    home = tmp_path / "cfg"
    home.mkdir()
    _mission_dir(home, "local/c")
    p = _manifest(home, f'[[vehicle]]\nname = "boat3"\nmissions = ["{store}/2026-06-*/", "local/c"]\n'
                        f'[[vehicle]]\nname = "boat4"\nmissions = ["{store / "2026-07-01a"}"]\n')
    man = load_manifest(p)
    got = [[m.path for m in v.missions] for v in man.vehicles]
    assert got == [[store / "2026-06-01a", store / "2026-06-01b", home / "local" / "c"],
                   [store / "2026-07-01a"]]
    assert man.vehicles[0].missions[0].entry == f"{store}/2026-06-*/"


@pytest.mark.parametrize("text, words", [
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/none"]\n', ["no such mission directory", "runs/none"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/a"]\n[[vehicle]]\nname = "v"\nmissions = ["runs/b"]\n',
     ["duplicate vehicle name", "'v'"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["../outside"]\n', ["holds no mission.toml", "outside"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["/nonexistent/abs/path"]\n',
     ["no such mission directory", "/nonexistent/abs/path"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/z*"]\n', ["matches no mission directory", "runs/z*"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/*", "runs/a"]\n', ["listed twice"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["odd/*"]\n', ["cannot name an output directory safely"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/a", "runs/./a"]\n', ["listed twice"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/a", "other/a"]\n', ["two missions named 'a'"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/empty"]\n', ["holds no mission.toml"]),
    ('[[vehicle]]\nname = "../x"\nmissions = ["runs/a"]\n', ["name must be"]),
    ('[[vehicle]]\nname = "v"\nmissions = []\n', ["non-empty list"]),
    ('[[vehicle]]\nname = "v"\nmissions = ["runs/a"]\nweight = 3\n', ["unknown key(s) weight"]),
    ('vehicle = 3\n', ["no [[vehicle]] table"]),
    ('[[vehicle]\n', ["not valid TOML"]),
])
def test_manifest_errors_name_what_and_where(tmp_path, text, words):
    _mission_dir(tmp_path, "runs/a")
    _mission_dir(tmp_path, "runs/b")
    _mission_dir(tmp_path, "odd/bad name")
    _mission_dir(tmp_path, "other/a")
    (tmp_path / "runs" / "empty").mkdir()
    (tmp_path.parent / "outside").mkdir(exist_ok=True)
    p = _manifest(tmp_path, text)
    with pytest.raises(ManifestError) as e:
        load_manifest(p)
    assert str(p) in str(e.value)
    for w in words:
        assert w in str(e.value)


def test_cli_reports_manifest_errors_without_traceback(tmp_path, capsys):
    p = _manifest(tmp_path, '[[vehicle]]\nname = "v"\nmissions = ["nowhere"]\n')
    assert main(["fleet", str(p), "--out", str(tmp_path / "out")]) == EXIT_DATA
    err = capsys.readouterr().err
    assert "aqfg fleet: error:" in err and "nowhere" in err and "Traceback" not in err
    assert main(["fleet", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == EXIT_DATA
    assert "no such manifest file" in capsys.readouterr().err


def test_differs_from_fleet_flags_the_odd_vehicle():
    rng = np.random.default_rng(0)
    C = np.array([np.diag([0.01, 0.02]) ** 2] * 8)
    X = np.array([1.0, 2.0]) + rng.normal(0, 1, (8, 2)) * np.array([0.01, 0.02])
    X[3] += [0.07, 0.0]                       # 7 sigma off in the first parameter
    t = differs_from_fleet(X, C)
    assert [o["differs"] for o in t] == [False, False, False, True, False, False, False, False]
    assert abs(t[3]["z"][0]) > 5 and t[3]["p_holm"] < 1e-6


# ---------------------------------------------------------------- on a LocalCluster
@pytest.fixture(scope="module")
def cluster():
    import logging

    from distributed import Client, LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as lc, Client(lc) as c:
        yield c


def _sim_vehicle(root, seeds, k_scale, duration=240.0):
    k = true_params("asv")["k"]
    paths = []
    for s in seeds:
        m, tr = simulate("asv", seed=s, duration=duration, gnss_period=8.0,
                         params={"k": k_scale * k})
        paths.append(save_mission(m, root / f"sim-{s}", truth=tr))
    return paths


def _assert_joint(fr_res, batch, tol=0.05, sig_rel=1e-6):
    """Within tol x the batch's model sigma (stricter than its sandwich-inflated sigma),
    fixed parameters and every mission's own; the same sigmas (model and inflated, within
    ``sig_rel``; the structural shift, linearised at the two solutions, within 2 %)."""
    sm = batch.sigma_model or batch.sigma
    st_f, st_b = fr_res.sigma_structure, batch.sigma_structure
    assert (st_f is None) == (st_b is None)
    assert st_f is None or st_b is None or st_f.effect == st_b.effect
    for n in batch.estimated:
        assert abs(fr_res.values[n] - batch.values[n]) < tol * sm[n], \
            (n, fr_res.values[n], batch.values[n], sm[n])
        if st_b is not None and n in st_b.shift:
            assert st_f is not None
            assert st_f.sigma_before[n] == pytest.approx(st_b.sigma_before[n], rel=1e-6)
            assert fr_res.sigma[n] == pytest.approx(batch.sigma[n], rel=0.02), n
            continue
        assert fr_res.sigma[n] == pytest.approx(batch.sigma[n], rel=sig_rel), n
        assert fr_res.sigma_model[n] == pytest.approx(sm[n], rel=sig_rel), n
    for m, pm in batch.per_mission.items():
        for n, e in pm.items():
            got = fr_res.per_mission[m][n]
            assert abs(got.value - e.value) < tol * sm[n]
            assert got.sigma == pytest.approx(e.sigma, rel=sig_rel), (m, n)


def test_a_worker_reads_a_mission_once_per_fit_and_uses_one_sent_to_it(tmp_path):
    """A worker keeps the missions it read for the fit (the same object for every step of
    it, whatever the solve), not for another fit, until the fit releases them; a mission
    sent from another worker is used instead of reading its files."""
    import dataclasses

    from aqfg.fleet import worker
    path = str(_sim_vehicle(tmp_path, (61,), 1.0, duration=60.0)[0])
    spec = worker.MissionSpec("run-a", "v", 0, "sim-61", path, True, FGSettings(), fit="fit-a")
    m = worker.load(spec)
    assert worker.load(dataclasses.replace(spec, run="run-b", refit=True)) is m
    other = worker.load(dataclasses.replace(spec, fit="fit-b"))
    assert other is not m and other.name == m.name
    assert worker.n_missions_read("fit-a") == worker.n_missions_read("fit-b") == 1
    assert worker.release_fit("fit-a") == 1 and worker.n_missions_read("fit-a") == 0
    assert worker.load(dataclasses.replace(spec, fit="fit-b")) is other
    worker.release_fit("fit-b")
    # sent from the worker that holds it: its files need not be readable here
    gone = dataclasses.replace(spec, path=str(tmp_path / "elsewhere"), fit="fit-c")

    class Fit:
        model = None
    fit = Fit()
    assert worker._vehicle([gone], fit, [m])[0] is m
    assert fit.model is not None               # the model it was fitted with, set on it
    assert worker.load(gone) is m
    worker.release_fit("fit-c")
    with pytest.raises(ValueError, match="no such mission directory"):
        worker.load(gone)                      # released: read again, and not there


def test_effect_document_writes_a_missing_fleet_cost_as_aqfg_fit_does():
    """A fleet cost that was not computed (no refit) is written as the shared fields are:
    null with a null_reason, not a bare null."""
    ae = EffectStep("linear_drag", adopted=False, p_value_robust=1e-4, cost_before=10.0,
                    base=BaseFit([], {}, {}), reason="refit not plausible",
                    fleet=FleetEffect(["otter"], cost_before=12.5, cost_after=float("nan")))
    doc = json.loads(dumps({"auto_effect": effect_document(ae)}))
    e = doc["auto_effect"]
    assert e["fleet_cost_before"] == 12.5
    assert e["fleet_cost_after"] is None and e["cost_after"] is None
    assert {"/auto_effect/fleet_cost_after", "/auto_effect/cost_after"} <= set(doc["null_reasons"])


@pytest.mark.slow
def test_fleet_equals_joint_fit_per_vehicle(tmp_path, cluster):
    """Two Otter missions (one vehicle, GNSS thinned to 8 s) and two simulated missions of
    a second vehicle: each vehicle's parameters equal fit_fg on its missions (the joint
    smoother, then its constants refined by prediction error)."""
    for n in ("otter-example", "otter-dev-calm-a"):
        os.symlink(data_path(n), tmp_path / n)
    _sim_vehicle(tmp_path, (21, 22), 1.15)
    p = write_manifest(tmp_path / "fleet.toml", {"otter": ["otter-example", "otter-dev-calm-a"],
                                                 "sim-asv": ["sim-21", "sim-22"]})
    man = load_manifest(p)
    fr = fit_fleet(man, cluster, gnss_every=8.0, timeout=300)
    # the missions the workers kept for the fit are dropped with it
    from aqfg.fleet import worker
    assert sum(cluster.run(worker.n_missions_read).values()) == 0
    # the fleet's effect step: the Otter's fits call for the linear drag, and one model
    # serves the fleet, so both vehicles are fitted with it; the step records the model-
    # as-given estimates
    for v in ("otter", "sim-asv"):
        ae = fr.results[v].effect_step
        assert ae is not None and ae.fleet is not None
        assert ae.adopted and ae.effect == "linear_drag", ae.reason
        assert fr.results[v].effects == ("linear_drag",)
        assert ae.fleet.vehicles_calling == ["otter"]
        assert ae.fleet.cost_after < ae.fleet.cost_before
    for name in ("otter-example", "otter-dev-calm-a"):
        truth = load_truth(data_path(name)).params
        cur = fr.results["otter"].per_mission[name]
        assert np.hypot(cur["s_x"].value - truth.get("s_x", 0.0),
                        cur["s_y"].value - truth.get("s_y", 0.0)) < 0.03, name
    for v in man.vehicles:
        ms = [with_gnss_every(load_mission(m.path), 8.0) for m in v.missions]
        # each vehicle equals fit_fg of its missions with the fleet's model
        ref = fit_fg(ms, effects=fr.results[v.name].effects,
                     settings=FGSettings().with_(batch={"auto_effect": False}))
        # (with the linear drag the two solvers' stopping points differ by up to a few
        # hundredths of a sigma, and the sigmas evaluated there by up to 0.5 % (k_yz,
        # poorly determined: sigma 5))
        _assert_joint(fr.results[v.name], ref, sig_rel=1e-2)
        d, e = fr.results[v.name].dead_reckoning, ref.dead_reckoning
        assert d.applied == e.applied and d.blocks == e.blocks, (d, e)
        # the tracks under the noise each mission's evidence chooses, as fit_fg's
        assert fr.results[v.name].track_noise_scale == ref.track_noise_scale
        for a, b in zip(fr.results[v.name].missions, ref.missions):
            assert np.max(np.abs(a.track.pos - b.track.pos)) < 0.05, a.name
    # outputs: per vehicle, per mission, fleet table with a test per vehicle, report
    out = tmp_path / "out"
    save_fleet(fr, out)
    table = json.loads((out / "fleet.json").read_text())
    assert table["parameters"] == ["k", "k_x", "k_yz", "linear_drag.c_x", "linear_drag.c_yz"]
    assert set(table["vehicles"]) == {"otter", "sim-asv"}
    for v in ("otter", "sim-asv"):
        par = json.loads((out / v / "parameters.json").read_text())
        assert par["format"] == "aqfg-parameters/1" and par["provenance"]["mode"] == "fleet"
        assert par["parameters"]["k"]["value"] == pytest.approx(fr.results[v].values["k"])
        assert par["dead_reckoning"]["applied"] == fr.results[v].dead_reckoning.applied
        assert par["auto_effect"]["adopted"] and par["auto_effect"]["effect"] == "linear_drag"
        assert "linear_drag.c_x" in par["parameters"]
        # the model-as-given estimates in aqfg fit's shape (a joint fit's: per_mission)
        wo = par["auto_effect"]["without_effect"]
        assert set(wo) == {"theta_e", "s_x", "s_y", "per_mission"}
        assert len(wo["per_mission"]) == 2
        assert all(set(e) == {"theta_e", "s_x", "s_y"} for e in wo["per_mission"].values())
        assert table["vehicles"][v]["test"]["differs"] is True, (      # Otter vs simulated ASV
            table["vehicles"][v]["test"], table["vehicles"][v]["parameters"])
    # the Otter (not the model): the constants it dead-reckons with predict as well as the
    # prediction-error refinement's (the smoother's own where the Wald test keeps them:
    # with the sway drag free of the paper vehicles' prior they predict within 1 %)
    dr = json.loads((out / "otter" / "parameters.json").read_text())["dead_reckoning"]
    pe = dr["prediction_error_m"]
    assert dr["applied"] or pe["median_before"] <= 1.02 * pe["median_after"], dr
    mp = json.loads((out / "sim-asv" / "sim-22" / "parameters.json").read_text())["parameters"]
    assert set(mp) == {"k", "k_x", "k_yz", "linear_drag.c_x", "linear_drag.c_yz", "theta_e",
                       "s_x", "s_y"}
    traj = np.loadtxt(out / "otter" / "otter-dev-calm-a" / "trajectory.csv", delimiter=",",
                      skiprows=1)
    assert traj.shape[1] == 7 and len(traj) > 500
    assert "sim-asv" in (out / "fleet.html").read_text()
    with pytest.raises(FileExistsError):
        save_fleet(fr, out)


@pytest.mark.slow
def test_worker_killed_mid_run_is_retried(tmp_path, cluster):
    """SIGKILL the worker process holding most of this run's missions between two rounds:
    its missions are served by the surviving or restarted worker (rebuilt from their paths
    or from a session it holds), and the result still equals the joint fit."""
    paths = _sim_vehicle(tmp_path, (31, 32, 33), 0.9)
    p = write_manifest(tmp_path / "fleet.toml", {"asv-killed": [x.name for x in paths]})
    killed = []

    def holds_missions():
        from aqfg.fleet import worker
        return worker.n_sessions("asv-killed")     # not stale ones of other tests

    def progress(frac, msg):
        # at the end of round 6 or later (every mission's session built and in use), the
        # worker holding the most missions is killed before the next round is sent
        if killed or not msg.startswith("round ") or "missions done" not in msg:
            return
        words = msg.split()
        done, total = words[2].split("/")
        if int(words[1].rstrip(":")) < 6 or done != total:
            return
        held = cluster.run(holds_missions)
        if not any(held.values()):
            return
        pids = cluster.run(os.getpid)
        addr = max(held, key=held.get)
        killed.append((pids[addr], held[addr], dict(held)))
        os.kill(pids[addr], signal.SIGKILL)
        t_end = time.monotonic() + 30.0
        while (pids[addr] in cluster.run(os.getpid, on_error="ignore").values()
               and time.monotonic() < t_end):
            time.sleep(0.1)
    # after a rebuild the iterates leave the batch's path, so both are run to tight
    # tolerances (the default stopping rule leaves up to ~0.1 sigma between two paths)
    # (the refinement of the constants after the joint solve is off: it runs once, after
    # the rounds, and is compared with fit_fg in the test above; so is the structural
    # sigma, which BatchSmoother.run leaves to fit_fg)
    tight = FGSettings().with_(solver={"rel_tol": 1e-12, "abs_tol": 1e-9},
                               batch={"dr_horizon": 0.0, "structural_sigma": False})
    fr = fit_fleet(load_manifest(p), cluster, settings=tight, progress=progress, timeout=120)
    assert killed and killed[0][1] >= 1, killed           # it held missions of this run
    assert killed[0][0] not in cluster.run(os.getpid).values()
    # (stats["rebuilt"] is not asserted: a mission may be served by a worker that still
    # holds an older session of it, which re-solves from the current fixed parameters)
    batch = BatchSmoother(settings=tight).run([load_mission(x) for x in paths])
    _assert_joint(fr.results["asv-killed"], batch)


@pytest.mark.slow
def test_cli_fleet_writes_outputs_and_refuses_to_overwrite(tmp_path, capsys):
    paths = _sim_vehicle(tmp_path, (41, 42), 1.0, duration=150.0)
    p = write_manifest(tmp_path / "fleet.toml", {"asv-a": [x.name for x in paths]})
    out = tmp_path / "out"
    assert main(["fleet", str(p), "--out", str(out), "--workers", "1", "--diagnose"]) == 0
    text = capsys.readouterr().out
    assert "asv-a" in text and "k_yz" in text
    for f in ("fleet.json", "fleet.html", "asv-a/parameters.json", "asv-a/sim-41/trajectory.csv",
              "asv-a/sim-42/inertial.csv"):
        assert (out / f).is_file(), f
    veh = json.loads((out / "fleet.json").read_text())["vehicles"]["asv-a"]
    assert veh["test"]["differs"] is None                       # one vehicle: no test
    # the simulator's physics is the model: each mission's diagnosis finds nothing missing
    assert [veh["diagnosis"][m]["missing"] for m in ("sim-41", "sim-42")] == [False, False]
    assert "Nothing missing" in (out / "fleet.html").read_text()
    assert main(["fleet", str(p), "--out", str(out), "--workers", "1"]) == 2
    assert "refusing to overwrite" in capsys.readouterr().err
    # the model's effects are in the outputs' provenance (the vehicle's and each mission's)
    out2 = tmp_path / "out2"
    assert main(["fleet", str(p), "--out", str(out2), "--workers", "1",
                 "--effect", "linear_drag"]) == 0
    veh = json.loads((out2 / "asv-a" / "parameters.json").read_text())
    assert veh["provenance"]["effects"] == ["linear_drag"] and "linear_drag.c_x" in veh["parameters"]
    mis = json.loads((out2 / "asv-a" / "sim-41" / "parameters.json").read_text())
    assert mis["provenance"]["effects"] == ["linear_drag"]


def test_a_local_cluster_runs_the_callers_work_while_its_workers_start_the_solver():
    """``fleet_client``'s ``while_starting`` runs once, before the block; the block gets
    every worker asked for, each with the solver already imported (Dask's preload)."""
    from aqfg.fleet.cluster import fleet_client
    calls = []
    with fleet_client(2, while_starting=lambda: calls.append(1)) as c:
        assert calls == [1]
        assert len(c.scheduler_info()["workers"]) == 2
        # (asked by a string, not a function of this module: unpickling one would import
        # this module, and the solver with it)
        loaded = c.run(eval, "'aqfg.fleet.worker' in __import__('sys').modules")
        assert list(loaded.values()) == [True, True]


def test_a_round_waits_for_a_worker_that_rejoins(monkeypatch):
    """A worker the scheduler dropped under load is restarted by its nanny: a round that
    finds none waits for one to (re)join instead of failing at once."""
    from aqfg.fleet import solve

    class FakeClient:
        def __init__(self):
            self.calls = 0
            self.waited = None

        def scheduler_info(self, n_workers=-1):
            self.calls += 1
            return {"workers": {} if self.calls == 1 else {"tcp://w1": {}}}

        def wait_for_workers(self, n, timeout=None):
            self.waited = (n, timeout)

    c = FakeClient()
    assert solve._alive_workers(c, wait=5.0) == ["tcp://w1"]
    assert c.waited == (1, 5.0)

    class NoneComes(FakeClient):
        def scheduler_info(self, n_workers=-1):
            return {"workers": {}}

        def wait_for_workers(self, n, timeout=None):
            raise TimeoutError("none")
    assert solve._alive_workers(NoneComes(), wait=0.1) == []
    with pytest.raises(solve.FleetError, match="no Dask worker"):
        solve._least_loaded([], {})


def test_missions_are_spread_by_size_largest_first(tmp_path):
    """A round's missions held by no worker go largest first to the worker holding the
    least data: one mission as large as three others together has a worker to itself."""
    from aqfg.fleet import solve
    from aqfg.fleet.worker import MissionSpec

    class TwoWorkers:
        def scheduler_info(self, n_workers=-1):
            return {"workers": {"tcp://a": {}, "tcp://b": {}}}
    sizes = (100, 300, 100, 100)
    specs = []
    for i, n in enumerate(sizes):
        d = tmp_path / f"m{i}"
        d.mkdir()
        (d / "gnss.csv").write_bytes(b"x" * 1000 * n)
        specs.append(MissionSpec("run", "v", i, f"m{i}", str(d), i == 0, FGSettings()))
    where: dict = {}
    chunks = solve._chunks(TwoWorkers(), {"v": [("open", {})] * 4}, {"v": specs}, where)
    held = {w: sorted(item[1].index for item in items) for w, items in chunks.items()}
    assert sorted(held.values()) == [[0, 2, 3], [1]]
    assert where[("v", 1)] != where[("v", 0)] == where[("v", 2)] == where[("v", 3)]


@pytest.mark.slow
def test_cli_fleet_no_auto_effect_fits_the_model_as_given(tmp_path, capsys):
    """An Otter vehicle, whose fit calls for the linear drag: `--no-auto-effect` keeps the
    model as given (no effect, no step recorded, no warning of one)."""
    os.symlink(data_path("otter-dev-calm-b"), tmp_path / "otter-dev-calm-b")
    p = write_manifest(tmp_path / "fleet.toml", {"otter": ["otter-dev-calm-b"]})
    out = tmp_path / "out"
    assert main(["fleet", str(p), "--out", str(out), "--workers", "1", "--gnss-every", "8",
                 "--no-auto-effect"]) == 0
    assert "added the effect" not in capsys.readouterr().err
    veh = json.loads((out / "otter" / "parameters.json").read_text())
    assert "auto_effect" not in veh and veh["provenance"]["effects"] == []
    assert set(veh["parameters"]) == {"k", "k_x", "k_yz"}


@pytest.mark.slow
def test_cli_fleet_on_a_separate_scheduler(tmp_path, capsys):
    """``--scheduler ADDRESS``: the fleet runs on a distributed scheduler it did not start
    (here one scheduler and one worker process on loopback), with a manifest that names its
    missions by an absolute glob, and leaves the cluster running for its owner."""
    import logging

    from distributed import Client, LocalCluster
    _sim_vehicle(tmp_path / "store", (51,), 1.0, duration=90.0)
    p = _manifest(tmp_path, f'[[vehicle]]\nname = "asv-s"\nmissions = ["{tmp_path}/store/sim-*"]\n')
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      scheduler_port=0, dashboard_address=None, silence_logs=logging.ERROR) as lc:
        out = tmp_path / "out"
        assert main(["fleet", str(p), "--out", str(out), "--scheduler", lc.scheduler_address,
                     "--no-auto-effect"]) == 0
        assert "asv-s" in capsys.readouterr().out
        assert (out / "asv-s" / "sim-51" / "trajectory.csv").is_file()
        with Client(lc.scheduler_address, timeout="10s") as c:   # still up, worker still there
            assert len(c.scheduler_info()["workers"]) == 1
    assert main(["fleet", str(p), "--out", str(tmp_path / "o2"),
                 "--scheduler", "tcp://127.0.0.1:9"]) == EXIT_DATA
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err

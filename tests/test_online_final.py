"""The final solve of an online no-ids run (backend/online_final.py): the online association
re-solved in batch at the log's stated noise."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from lampsam.backend.config import ReassociationConfig, SlamConfig
from lampsam.backend.graph_log import run_graph_log, run_graph_log_backend
from lampsam.backend.interface import SlamResult
from lampsam.backend.online_final import final_solve, online_association
from lampsam.backend.reassociate import Sightings
from lampsam.cli import main
from lampsam.datasets.graph_text import GraphLog, read_graph_text
from lampsam.datasets.landmark_log_sim import LandmarkLogSpec, write_landmark_log
from lampsam.datasets.tum import read_tum

#: 200 poses of 0.5 m among 30 trees in a 40 m square: the online iSAM2 pass at 16x the
#: stated odometry variance associates every sighting it records to its own tree
#: (checked below), and its poses are 0.04 m RMS from the batch at the stated noise
SPEC = LandmarkLogSpec(n_poses=200, n_landmarks=30, extent=40.0, stop_every=0)


def _log(tmp_path: Path) -> GraphLog:
    path, _ = write_landmark_log(tmp_path / "log.txt", SPEC, np.random.default_rng(1))
    return read_graph_text(path)


def _inflated(cfg: SlamConfig, q: float = 16.0) -> SlamConfig:
    return dataclasses.replace(cfg, pose2_odometry=dataclasses.replace(cfg.pose2_odometry,
                                                                       cov_scale=q))

#: The config with the held sightings' placement off (``online_final_held_mixture``, on by
#: default): these tests check the final solve of the association the online run made.
NO_PLACE = dataclasses.replace(SlamConfig(), reassociation=dataclasses.replace(
    SlamConfig().reassociation, online_final_held_mixture=False))


def _file_ids(g: GraphLog, s: Sightings) -> np.ndarray:
    """(S,) the file's id of each sighting (same pose, same range)."""
    return np.array([min(g.sightings[k], key=lambda c: abs(c.range - z[1])).landmark
                     for k, z in zip(s.k.tolist(), s.z, strict=True)])


def _one_to_one(lid: np.ndarray, fid: np.ndarray) -> bool:
    """Every landmark holds one file id and every file id one landmark."""
    return (all(len(set(fid[lid == i].tolist())) == 1 for i in np.unique(lid))
            and all(len(set(lid[fid == f].tolist())) == 1 for f in np.unique(fid)))


def _known_batch(g: GraphLog, s: Sightings) -> SlamResult:
    """lampsam's known-id batch at the stated noise on the log cut to the sightings in
    ``s`` (the online pass leaves a few out, between its gate and the new-landmark
    threshold)."""
    kept = [[x for x in ss if any(int(k) == kk and abs(float(z[1]) - x.range) < 1e-9
                                  for k, z in zip(s.k.tolist(), s.z, strict=True))]
            for kk, ss in enumerate(g.sightings)]
    return run_graph_log(dataclasses.replace(g, sightings=kept), "batch", SlamConfig())


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


@pytest.fixture(scope="module")
def online_run(tmp_path_factory: pytest.TempPathFactory
               ) -> tuple[GraphLog, SlamResult, Sightings]:
    g = _log(tmp_path_factory.mktemp("online_final"))
    online, be = run_graph_log_backend(g, "isam2", _inflated(NO_PLACE), known_ids=False)
    assert be is not None and online.status == "ok"
    return g, online, online_association(be, online)


def test_final_solve_of_a_right_association_is_the_known_id_batch(
        online_run: tuple[GraphLog, SlamResult, Sightings]) -> None:
    """The online pass at 16x the odometry variance gets the association right (each of
    its landmarks one tree, each tree one landmark) but its poses are those of the
    inflated noise (> 0.02 m RMS from the batch at the stated noise); the final solve
    at the stated noise keeps the association and its poses equal the known-id batch
    on the same sightings within 1 mm (measured 1e-5 m: LM's stopping tolerances)."""
    g, online, s0 = online_run
    s = Sightings(s0.k.copy(), s0.z, s0.r, s0.lid.copy())
    fid = _file_ids(g, s)
    assert _one_to_one(s.lid, fid)
    assert len(s.k) > 0.99 * sum(len(ss) for ss in g.sightings)
    known = _known_batch(g, s)
    assert _rms(online.poses, known.poses) > 0.02
    run = final_solve(g, _inflated(NO_PLACE), online, s)
    assert _one_to_one(run.sightings.lid, fid)
    assert run.scale == 16.0
    assert float(np.abs(run.poses[:, :2] - known.poses[:, :2]).max()) < 1e-3
    assert len(run.mapped()) == len(known.landmarks)


def test_final_solve_merges_a_duplicate_of_the_online_pass(
        online_run: tuple[GraphLog, SlamResult, Sightings]) -> None:
    """The online association with one tree mapped twice (its sightings after the
    longest gap between two of them, at least 30 poses, moved to a new landmark, as a
    missed revisit does): the final solve merges the copy (every landmark one tree,
    every tree one landmark) and its poses equal the known-id batch within 1 mm."""
    g, online, s0 = online_run
    fid = _file_ids(g, s0)
    best: tuple[int, int, int] = (0, -1, -1)  # (gap, tree, pose after the gap)
    for f in np.unique(fid).tolist():
        ks = np.sort(s0.k[fid == f])
        if len(ks) >= 6:
            j = int(np.argmax(np.diff(ks)))
            if min(j + 1, len(ks) - j - 1) >= 3 and int(ks[j + 1] - ks[j]) > best[0]:
                best = (int(ks[j + 1] - ks[j]), f, int(ks[j + 1]))
    gap, tree, after = best
    assert gap >= 30
    lid = s0.lid.copy()
    lid[(fid == tree) & (s0.k >= after)] = int(lid.max()) + 1
    s = Sightings(s0.k.copy(), s0.z, s0.r, lid)
    assert not _one_to_one(s.lid, fid)
    run = final_solve(g, _inflated(NO_PLACE), online, s)
    assert _one_to_one(run.sightings.lid, fid)
    known = _known_batch(g, s0)
    assert float(np.abs(run.poses[:, :2] - known.poses[:, :2]).max()) < 1e-3


def test_cli_writes_the_final_solve_and_the_online_poses(tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    """``lampsam slam LOG --no-ids --backend isam2``: ``trajectory.tum`` is the final solve,
    ``online.tum`` the online poses (different files, same steps), the summary says which
    is which and counts the final solve's moves; ``online_final = false`` writes the
    online run alone, as before. ``--g2o`` writes the final solve's graph. (One online
    setting, ``online_candidates = []``: the picker is tested in test_online_picker.)"""
    path, tpath = write_landmark_log(tmp_path / "log.txt", dataclasses.replace(
        SPEC, n_poses=120), np.random.default_rng(2))
    out = tmp_path / "out"
    (tmp_path / "one.toml").write_text("[reassociation]\nonline_candidates = []\n")
    assert main(["slam", str(path), "--no-ids", "--backend", "isam2", "--truth", str(tpath),
                 "--config", str(tmp_path / "one.toml"), "--out", str(out),
                 "--g2o", str(tmp_path / "final.g2o")]) == 0
    assert "EDGE_SE2_XY" in (tmp_path / "final.g2o").read_text()  # the final solve's graph
    s = json.loads((out / "summary.json").read_text())
    assert s["online_final"] == 1.0 and set(s["trajectory"]) == {"trajectory.tum", "online.tum"}
    assert {"noids_cost", "noids_merges", "online_cpu_s", "online_final_cpu_s"} <= set(s)
    final, online = read_tum(out / "trajectory.tum"), read_tum(out / "online.tum")
    assert final.poses.shape == online.poses.shape and not np.allclose(final.poses, online.poses)
    assert s["error"]["position_rms_m"] < 0.2 and s["online_error"]["position_rms_m"] < 0.5
    assert "final solve of the online isam2 run's association" in capsys.readouterr().out
    (tmp_path / "c.toml").write_text("[reassociation]\nonline_final = false\n")
    out2 = tmp_path / "out2"
    assert main(["slam", str(path), "--no-ids", "--backend", "isam2", "--config",
                 str(tmp_path / "c.toml"), "--out", str(out2)]) == 0
    assert not (out2 / "online.tum").exists()
    assert np.allclose(read_tum(out2 / "trajectory.tum").poses, online.poses)
    assert "online_final" not in json.loads((out2 / "summary.json").read_text())


def test_online_final_options_are_checked() -> None:
    with pytest.raises(Exception, match="online_final_cov_scale"):
        SlamConfig.from_dict({"reassociation": {"online_final_cov_scale": 0.0}})
    assert ReassociationConfig().online_final and ReassociationConfig().online_final_passes == 20


def test_online_association_maps_keyframes_to_poses_and_follows_revisit_ties() -> None:
    """A graph backend records sightings by keyframe (0 the start pose; keyframe j >= 1 is
    the j-th step that made one) and its revisit check's merges as ties (copy -> old,
    possibly chained): the association has log poses and the old landmark's id."""

    class _Graph:
        name = "isam2"
        planar_sightings = [(1, np.array([0.1, 5.0]), np.eye(2), 7),
                            (2, np.array([0.2, 4.0]), np.eye(2), 8),
                            (3, np.array([0.3, 3.0]), np.eye(2), 9)]
        revisit_ties = [(3, 9, 8), (3, 8, 7)]

    res = SlamResult(backend="isam2", times=np.arange(6.0), poses=np.zeros((6, 3)),
                     pose_covs=np.zeros((6, 3, 3)), landmarks=[], step_times_s=np.zeros(6),
                     keyframes=np.array([False, True, False, True, True, False]))
    s = online_association(_Graph(), res)  # type: ignore[arg-type]
    assert s.k.tolist() == [1, 3, 4] and s.lid.tolist() == [7, 7, 7]
    assert s.z.shape == (3, 2) and s.r.shape == (3, 2, 2)


def test_a_failed_final_solve_keeps_the_online_answer(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """GTSAM throwing in the final solve (or SIGINT during it) leaves the finished online
    run as the answer, marked ``online_final`` 0, instead of losing it."""
    import lampsam.backend.online_final as of

    def boom(*_: object, **__: object) -> None:
        raise RuntimeError("Indeterminant linear system")

    monkeypatch.setattr(of, "final_solve", boom)
    g = read_graph_text(write_landmark_log(tmp_path / "log.txt", dataclasses.replace(
        SPEC, n_poses=60), np.random.default_rng(3))[0])
    final, online = of.run_online_final(g, "isam2", NO_PLACE)
    assert final is online and online.status == "ok" and online.extra["online_final"] == 0.0


def test_singletons_add_every_sighting_the_online_run_left_out(
        online_run: tuple[GraphLog, SlamResult, Sightings]) -> None:
    """``online_final_singletons``: the sightings the online run did not record (2 of
    2,228 here) join the association, each as a landmark of its own with a new id; the
    recorded ones keep theirs."""
    from lampsam.backend.online_final import with_singletons

    g, _, s0 = online_run
    s = with_singletons(g, s0)
    n_all = sum(len(ss) for ss in g.sightings)
    extra = len(s.k) - len(s0.k)
    assert len(s.k) == n_all and extra > 0
    assert np.array_equal(s.lid[: len(s0.k)], s0.lid)
    new = s.lid[len(s0.k):]
    assert len(set(new.tolist())) == extra and new.min() > s0.lid.max()


def test_an_online_run_that_stopped_mid_log_is_written_as_it_is(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An online run that failed or was stopped mid-log (status not ok; its last keyframe's
    sightings point past the keyframes it kept) is the answer as it is, ``online_final`` 0:
    was an IndexError in reading its association (found on the held-out loop log)."""
    import lampsam.backend.online_final as of

    real = of.run_graph_log_backend

    def stopped(*args: object, **kwargs: object):  # type: ignore[no-untyped-def]
        result, be = real(*args, **kwargs)  # type: ignore[arg-type]
        keep = np.flatnonzero(result.keyframes)[-5]  # the last few keyframes lost
        kf = result.keyframes.copy()
        kf[keep:] = False
        return dataclasses.replace(result, status="failed", keyframes=kf), be

    monkeypatch.setattr(of, "run_graph_log_backend", stopped)
    g = read_graph_text(write_landmark_log(tmp_path / "log.txt", dataclasses.replace(
        SPEC, n_poses=60), np.random.default_rng(3))[0])
    final, online = of.run_online_final(g, "isam2", NO_PLACE)
    assert final is online and online.status == "failed"
    assert online.extra["online_final"] == 0.0

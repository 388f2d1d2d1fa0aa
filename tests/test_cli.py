"""The open3d-pnerf command line, run in-process through cli.main (and once as a console script)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from open3d_pnerf import cli

COMMANDS = ("demo", "reconstruct", "extend", "map", "track", "tsdf", "render", "evaluate", "formats")


@pytest.mark.slow
def test_help_lists_every_command():
    out = subprocess.run([sys.executable, "-m", "open3d_pnerf.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    for command in COMMANDS:
        assert command in out.stdout


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([command, "--help"])
    assert exc.value.code == 0
    assert "usage" in capsys.readouterr().out


def test_formats_lists_every_layout_load_sequence_detects_in_its_order(capsys):
    from open3d_pnerf.data import FORMATS

    assert cli.main(["formats"]) == 0
    out = capsys.readouterr().out
    positions = [out.index(f"{fmt.name}: {fmt.layout}") for fmt in FORMATS]
    assert len(FORMATS) >= 5 and positions == sorted(positions)


def test_missing_folder_is_one_clear_line(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert cli.main(["--quiet", "track", str(missing), "--out", str(tmp_path / "o")]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error" in err[0] and str(missing) in err[0]


def test_bad_frames_spec(tmp_path, capsys):
    code = cli.main(["--quiet", "track", "sample", "--frames", "a:b", "--out", str(tmp_path)])
    assert code == cli.EXIT_ERROR and "--frames" in capsys.readouterr().err


def test_track_writes_trajectories(tmp_path, capsys):
    assert cli.main(["--quiet", "track", "sample", "--frames", "0:6", "--out", str(tmp_path)]) == 0
    poses = np.load(tmp_path / "poses.npy")
    assert poses.shape == (6, 4, 4) and np.load(tmp_path / "covariances.npy").shape == (6, 6, 6)
    assert len((tmp_path / "trajectory_tum.txt").read_text().splitlines()) == 7  # header + 6
    assert "ATE RMSE" in capsys.readouterr().out


def test_tsdf_writes_mesh(tmp_path):
    assert cli.main(["--quiet", "tsdf", "sample", "--gt-poses", "--out", str(tmp_path)]) == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """One short `reconstruct` run on the sample (test preset, 40 steps, frames 0, 4, 8 held out)."""
    out = tmp_path_factory.mktemp("cli") / "run"
    args = ["--quiet", "reconstruct", "sample", "--gt-poses", "--preset", "test", "--holdout-every", "4",
            "--max-steps", "40", "--out", str(out)]
    assert cli.main(args) == 0
    return out


@pytest.mark.slow
def test_reconstruct_render_and_resume(run_dir, tmp_path):
    out = run_dir
    for name in ("model.pt", "reconstruction.json", "trajectory_tum.txt", "trajectory.log", "report.md",
                 "report.json", "checkpoints/checkpoint.pt"):
        assert (out / name).is_file(), name
    report = json.loads((out / "report.json").read_text())
    assert report["training"]["steps"] == 40 and "model" in report["scores"] and "tsdf" in report["scores"]

    assert cli.main(["--quiet", "render", str(out), "--pose", "1", "--out", str(tmp_path / "view.png")]) == 0
    image = cv2.imread(str(tmp_path / "view.png"))
    assert image.shape == (120, 160, 3)  # the training intrinsic: image_scale 0.5 of 320x240
    depth = cv2.imread(str(tmp_path / "view_depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and np.median(depth[depth > 0]) > 300  # mm, a room-scale scene

    # resume continues the saved schedule: raise the step budget in the saved run config
    config_path = out / "run_config.json"
    saved = json.loads(config_path.read_text())
    saved["config"]["max_steps"] = 50
    config_path.write_text(json.dumps(saved))
    assert cli.main(["--quiet", "reconstruct", "--resume", str(out)]) == 0
    assert json.loads((out / "report.json").read_text())["training"]["steps"] == 50


def test_resume_needs_a_run_folder(tmp_path, capsys):
    assert cli.main(["--quiet", "reconstruct", "--resume", str(tmp_path)]) == cli.EXIT_ERROR
    assert "run_config.json" in capsys.readouterr().err


def test_render_rejects_bad_pose(tmp_path, capsys):
    assert cli.main(["--quiet", "render", str(tmp_path), "--pose", "0", "--out", str(tmp_path / "x.png")]) == 2
    assert "reconstruction.json" in capsys.readouterr().err


@pytest.mark.skipif(shutil.which("open3d-pnerf") is None and not (Path(sys.executable).parent / "open3d-pnerf").exists(),
                    reason="console script not installed")
@pytest.mark.slow
def test_console_script_installed():
    exe = shutil.which("open3d-pnerf") or str(Path(sys.executable).parent / "open3d-pnerf")
    out = subprocess.run([exe, "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "reconstruct" in out.stdout


@pytest.mark.slow
def test_evaluate_scores_the_held_out_frames_like_reconstruct(run_dir, tmp_path, capsys):
    target = tmp_path / "eval.json"
    assert cli.main(["--quiet", "evaluate", str(run_dir), "--out", str(target)]) == 0
    report = json.loads(target.read_text())
    assert report["holdout_frames"] == [0, 4, 8]
    # the same renders and the same TSDF (training frames and poses) as reconstruct's report; the
    # exported mesh is read back from its PLY (8-bit vertex colours)
    reported = json.loads((run_dir / "report.json").read_text())["scores"]
    assert list(report["scores"]) == list(reported) == ["model", "mesh", "sensor", "tsdf", "tsdf_default"]
    for method, row in reported.items():
        assert report["scores"][method] == (row if method != "mesh" else pytest.approx(row, abs=5e-3)), method
    out = capsys.readouterr().out
    assert "model (the field's renders)" in out and "Open3D TSDF, same threshold" in out and str(target) in out


@pytest.mark.slow
def test_evaluate_a_folder_saved_from_python_scores_its_frames_else_needs_data(run_dir, tmp_path, capsys):
    folder = tmp_path / "saved"
    shutil.copytree(run_dir, folder, ignore=shutil.ignore_patterns("checkpoints", "run_config.json"))
    assert cli.main(["--quiet", "evaluate", str(folder), "--no-tsdf"]) == 0  # the frames saved with it
    from_frames = json.loads((folder / "evaluation.json").read_text())["scores"]["model"]
    assert cli.main(["--quiet", "evaluate", str(folder), "--data", "sample", "--no-tsdf"]) == 0
    report = json.loads((folder / "evaluation.json").read_text())
    assert set(report["scores"]) == {"model"} and report["scores"]["model"]["psnr"] > 5
    assert from_frames["psnr"] == pytest.approx(report["scores"]["model"]["psnr"], abs=0.05)  # PNG round trip
    shutil.rmtree(folder / "frames")
    assert cli.main(["--quiet", "evaluate", str(folder)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--data" in err[0]


@pytest.mark.slow
def test_evaluate_missing_data_is_one_clear_line(run_dir, tmp_path, capsys):
    missing = tmp_path / "moved"
    assert cli.main(["--quiet", "evaluate", str(run_dir), "--data", str(missing)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0]
    folder = tmp_path / "copy"
    shutil.copytree(run_dir, folder, ignore=shutil.ignore_patterns("checkpoints", "frames"))  # frames: its own data
    saved = json.loads((folder / "run_config.json").read_text())
    (folder / "run_config.json").write_text(json.dumps({**saved, "data": str(missing)}))
    assert cli.main(["--quiet", "evaluate", str(folder)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "run_config.json" in err[0] and "--data" in err[0]


def test_evaluate_rejects_a_folder_that_is_not_a_reconstruction(tmp_path, capsys):
    assert cli.main(["--quiet", "evaluate", str(tmp_path)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reconstruction.json" in err[0]


def test_refine_poses_option_reaches_the_config():
    parser = cli.build_parser()
    assert cli._config(parser.parse_args(["reconstruct", "sample", "--refine-poses"])).refine_poses is True
    assert cli._config(parser.parse_args(["reconstruct", "sample"])).refine_poses is False


@pytest.mark.slow
def test_the_cli_and_the_python_api_track_the_same_data_the_same_way(tmp_path):
    """One pipeline: `reconstruct` on the command line and pn.reconstruct() give the same poses
    and covariances for the same input and settings (here a non-default covariance scale)."""
    import open3d_pnerf as pn

    out = tmp_path / "cli"
    args = ["--quiet", "reconstruct", "sample", "--frames", "0:6", "--preset", "test", "--max-steps", "2",
            "--set", "tracking.loop_closure=false", "--out", str(out)]
    assert cli.main(args) == 0
    config = pn.ReconstructionConfig.preset("test", max_steps=2, progress=False, **{"tracking.loop_closure": False})
    recon = pn.reconstruct(pn.load_sample().select(range(6)), config)
    # equal up to the summation order of Open3D's multi-threaded odometry: its last bits vary from run to
    # run, usually leaving the refinement's answers nanometres apart, but now and then they flip one of its
    # stopping decisions (a step just at a fraction of the answer's sigma), which moves a pose by a fraction
    # of its sigma (1 mm, 0.04 and 0.84 mrad seen): the poses are held to half their own sigma (Mahalanobis
    # distance of the difference under the pose's covariance), far below the tracker's error, far above a
    # nanometre; the covariances to 10% of the scale of each element (sqrt(C_ii C_jj)): a cross term near zero
    # moves by more than 10% of itself (-6.1e-10 vs -9.9e-10 against variances near 1e-6 seen), where loop
    # closures on and off differ by up to 25% on these frames
    from scipy.spatial.transform import Rotation

    delta = np.linalg.inv(recon.poses) @ np.load(out / "poses.npy")  # right perturbations
    # frame 0 is the origin of the depth cameras, but these are colour-camera poses (its offset solved with
    # the others) and it has no covariance of its own: held to 0.5 mrad / 2 mm (0.04 mrad / 0.16 mm seen)
    assert np.abs(delta[0, :3, :3] - np.eye(3)).max() < 5e-4 and np.abs(delta[0, :3, 3]).max() < 2e-3
    for step, cov in zip(delta[1:], recon.covariances[1:]):
        x = np.concatenate([Rotation.from_matrix(step[:3, :3]).as_rotvec(), step[:3, 3]])
        assert x @ np.linalg.solve(cov, x) < 0.5**2
    cli_cov, api_cov = np.load(out / "covariances.npy"), recon.covariances
    std = np.sqrt(np.diagonal(api_cov, axis1=1, axis2=2))
    assert (np.abs(cli_cov - api_cov) <= 0.1 * std[:, :, None] * std[:, None, :] + 1e-15).all()
    # the setting reached both: with the default loop closures the covariances differ
    default = pn.track(pn.load_sample().select(range(6)), progress=False)
    assert not np.allclose(recon.covariances, default.covariances)


def test_set_reaches_the_config_and_rejects_unknown_names(capsys):
    parser = cli.build_parser()
    config = cli._config(parser.parse_args(["reconstruct", "sample", "--set", "sampling.n_coarse=24",
                                            "--set", "grid.resolutions=[8, 16]", "--set", "field=grid"]))
    assert config.sampling.n_coarse == 24 and config.grid.resolutions == (8, 16) and config.field == "grid"
    assert cli.main(["--quiet", "reconstruct", "sample", "--set", "sampling.n=8"]) == cli.EXIT_ERROR
    assert "sampling.n" in capsys.readouterr().err
    assert cli.main(["--quiet", "reconstruct", "sample", "--set", "n_coarse"]) == cli.EXIT_ERROR
    assert "KEY=VALUE" in capsys.readouterr().err


def test_ctrl_c_during_training_exits_130_saying_how_to_resume_or_finish(tmp_path, capsys, monkeypatch):
    from open3d_pnerf.training import Trainer

    real = Trainer.train_step

    def train_step(self):
        if self.step == 2:
            raise KeyboardInterrupt
        return real(self)

    monkeypatch.setattr(Trainer, "train_step", train_step)
    out = tmp_path / "run"
    args = ["--quiet", "reconstruct", "sample", "--frames", "0:4", "--gt-poses", "--preset", "test", "--max-steps", "8",
            "--out", str(out)]
    assert cli.main(args) == cli.EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "after training step 2" in err and f"--resume {out}" in err and "--finish" in err
    assert not (out / "mesh.ply").exists()  # no export after an interrupt
    monkeypatch.undo()
    assert cli.main(["--quiet", "reconstruct", "--resume", str(out), "--finish"]) == 0
    assert json.loads((out / "report.json").read_text())["training"]["steps"] == 2
    assert (out / "model.pt").is_file() and (out / "trajectory.json").is_file() and (out / "report.md").is_file()
    with pytest.raises(SystemExit):  # --finish needs --resume
        cli.main(["reconstruct", "sample", "--finish"])


@pytest.mark.slow
def test_insisting_on_a_kernel_that_cannot_run_is_one_config_error_before_any_work(tmp_path):
    """hashgrid.backend=kernel where the kernel cannot run (here: turned off) fails at the config,
    before tracking or targets, as one line; in Python, as a ConfigError from validate()."""
    env = {**os.environ, "PNERF_NATIVE": "0"}
    run = subprocess.run([sys.executable, "-m", "open3d_pnerf.cli", "--quiet", "reconstruct", "sample", "--out",
                          str(tmp_path / "out"), "--set", "hashgrid.backend=kernel"], env=env, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == cli.EXIT_ERROR
    err = run.stderr.strip().splitlines()
    assert len(err) == 1 and "hashgrid.backend='kernel'" in err[0] and "PNERF_NATIVE=0" in err[0], run.stderr
    assert not (tmp_path / "out" / "tracking").exists()
    script = ("import open3d_pnerf as pn\n"
              "try:\n    pn.ReconstructionConfig().replace(**{'hashgrid.backend': 'kernel'})\n"
              "except pn.errors.ConfigError as exc:\n    print('ConfigError', exc)\n")
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert run.stdout.startswith("ConfigError config field hashgrid.backend='kernel'"), run.stdout + run.stderr

"""The streaming Mapper on the bundled sample's real frames (320x240): tracking as frames come,
keyframes, a renderable map at any moment, saving and resuming, bad input, `open3d-pnerf map`."""

import json

import numpy as np
import pytest

from open3d_pnerf import Mapper, Reconstruction, ReconstructionConfig, absolute_trajectory_error, track
from open3d_pnerf.cli import main
from open3d_pnerf.errors import CheckpointError, InputError, TrackingError
from open3d_pnerf.synthetic import synthetic_sequence


def config(**changes):
    return ReconstructionConfig.preset("test", holdout_every=4, progress=False, **{
        "mapping.keyframe_every": 2, "mapping.train_s_per_frame": 0.01, **changes})


@pytest.fixture(scope="module")
def mapped(sample):
    mapper = Mapper(sample.intrinsic, config())
    out = [mapper.add(sample.to_open3d(i), sample.timestamps[i]) for i in range(8)]
    return mapper, out


@pytest.mark.slow
def test_every_frame_is_tracked_as_it_comes_with_a_growing_covariance(sample, mapped):
    mapper, out = mapped
    poses = np.stack([pose for pose, _ in out])
    assert len(mapper) == 8 and poses.shape == (8, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4))
    batch = track(sample[:8], progress=False)
    assert absolute_trajectory_error(poses, sample.gt_poses[:8])["rmse"] < 2 * absolute_trajectory_error(
        batch.poses, sample.gt_poses[:8])["rmse"] + 1e-3
    sd = np.array([np.sqrt(np.diag(c)[3:]) for _, c in out])
    assert not sd[0].any() and (sd[1:] > 0).all() and sd[-1].min() > sd[1].max()  # uncertainty grows along the chain
    assert mapper.keyframes == [0, 2, 4, 6] and mapper.holdout == [1, 3, 5, 7]
    assert set(mapper.frames.images) == {0, 1, 2, 3, 4, 5, 6, 7}  # kept: keyframes, held-out, the last two
    training = mapper.summary()["seconds"]["training"]
    assert mapper.steps > 0 and training > 0
    # the per-frame budget holds on average: a step longer than the budget is repaid by the next frames
    # (every frame training at least one step, as before, would spend 8 steps against 0.08 s here)
    assert training <= 8 * 0.01 + 3 * training / mapper.steps


@pytest.mark.slow
def test_the_maps_occupancy_grid_follows_the_frames_and_is_kept_until_they_change(sample):
    mapper = Mapper(sample.intrinsic, config())
    for i in range(6):
        mapper.add(sample.to_open3d(i), sample.timestamps[i])
    grid = mapper.occupancy_grid(0.1)
    assert mapper.occupancy_grid(0.1) is grid  # nothing new: the same grid, not built again
    seen = (~grid.unknown()).sum()
    mapper.add(sample.to_open3d(6), sample.timestamps[6])  # a keyframe: one more view, more training
    again = mapper.occupancy_grid(0.1)
    assert again is not grid and not np.array_equal(again.log_odds, grid.log_odds)
    assert (~again.unknown()).sum() > 0.5 * seen
    assert mapper.occupancy_grid(0.2) is not again


@pytest.mark.slow
def test_the_map_is_a_reconstruction_at_any_moment(sample, mapped):
    mapper, _ = mapped
    recon = mapper.reconstruction(export=False)
    assert isinstance(recon, Reconstruction) and len(recon.poses) == 8
    np.testing.assert_array_equal(recon.train_indices, [0, 2, 4, 6])
    np.testing.assert_array_equal(recon.holdout_indices, [1, 3, 5, 7])
    out = recon.render(recon.poses[1])
    assert out["color"].shape == (120, 160, 3) and np.isfinite(out["depth"]).all()
    steps = mapper.steps
    mapper.train(0.05)  # the map returned before is a copy: training on does not change it
    assert mapper.steps > steps
    again = recon.render(recon.poses[1])
    np.testing.assert_array_equal(out["depth"], again["depth"])


@pytest.mark.slow
def test_a_saved_mapper_resumes_on_the_map_and_refuses_frames_it_cannot_place(sample, mapped, tmp_path):
    mapper, _ = mapped
    folder = mapper.save(tmp_path / "map", mapper.reconstruction(export=False))
    resumed = Mapper.resume(folder)
    assert len(resumed) == 8 and resumed.keyframes == [0, 2, 4, 6]
    room = synthetic_sequence(1, 320, 240).sequence[0]
    with pytest.raises(TrackingError, match="registers to none of the map's frames"):
        resumed.add((room.color, room.depth))
    assert len(resumed) == 8  # the refused frame left nothing behind
    pose, covariance = resumed.add(sample.to_open3d(8), sample.timestamps[8])
    placed = [e for e in resumed.chain.edges if e.target == 8 and e.success]
    assert placed and placed[0].source < 8
    assert np.linalg.norm(pose[:3, 3] - mapper.poses[7][:3, 3]) < 0.05
    assert (np.diag(covariance) > 0).all()
    with pytest.raises(CheckpointError, match="mapper.json"):
        Mapper.resume(tmp_path)


def test_bad_frames_are_named_errors(sample):
    mapper = Mapper(sample.intrinsic, config())
    with pytest.raises(InputError, match="RGBDImage or a \\(color, depth\\) pair"):
        mapper.add("frame.png")
    small = sample.at_scale(0.5)[0]
    with pytest.raises(InputError, match="expected uint8"):
        mapper.add((small.color, small.depth))
    frame = sample[0]
    with pytest.raises(InputError, match="depth is"):
        mapper.add((frame.color, frame.depth[:100]))
    mapper.add((frame.color, frame.depth), 5.0)
    with pytest.raises(InputError, match="does not follow"):
        mapper.add((frame.color, frame.depth), 5.0)
    with pytest.raises(InputError, match="depth_scale"):
        Mapper(sample.intrinsic, depth_scale=0)


@pytest.mark.slow
def test_cli_map_feeds_a_recorded_folder_as_if_live(tmp_path):
    out = tmp_path / "map"
    assert main(["--quiet", "map", "sample", "--out", str(out), "--preset", "test", "--holdout-every", "4",
                 "--finish", "1", "--set", "mapping.keyframe_every=2"]) == 0
    report = json.loads((out / "map_report.json").read_text())
    assert report["frames"] == 11 and report["keyframes"] == 6 and report["frames_per_s"] > 0
    assert report["heldout"]["psnr"] > 5
    assert {"mesh.ply", "frames", "mapper.json", "reconstruction.json"} <= {p.name for p in out.iterdir()}
    assert len(Mapper.resume(out)) == 11


def test_cli_map_needs_data_or_a_camera_and_an_azure_kinect_needs_its_intrinsic(tmp_path, capsys):
    assert main(["--quiet", "map", "--out", str(tmp_path)]) == 2
    assert main(["--quiet", "map", "--camera", "azure-kinect", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "needs DATA" in err[0] and "--intrinsic" in err[1]

"""A map that grows: concatenated sequences, tracking onto a map, a field that grows its box,
Reconstruction.extend and `open3d-pnerf extend` (on the bundled sample: real frames)."""

import json

import numpy as np
import open3d as o3d
import pytest
import torch

from open3d_pnerf import Reconstruction, ReconstructionConfig, absolute_trajectory_error, reconstruct, track
from open3d_pnerf.cli import EXIT_ERROR, main
from open3d_pnerf.data import concatenate
from open3d_pnerf.errors import CheckpointError, ConfigError, InputError, TrackingError
from open3d_pnerf.fields import BlockEncoding, HashGridConfig, block_boxes, block_table_size, block_tables, grow
from open3d_pnerf.synthetic import synthetic_sequence
from open3d_pnerf.tracking import track_onto

FIRST, REST = slice(0, 6), slice(6, 11)


def test_concatenate_keeps_every_frame_in_order(sample):
    joined = concatenate([sample[FIRST], sample[REST]])
    assert len(joined) == 11 and joined.image_size == sample.image_size
    np.testing.assert_allclose(joined.K, sample.K)
    np.testing.assert_array_equal(joined.timestamps, sample.timestamps)
    np.testing.assert_allclose(joined.gt_poses, sample.gt_poses)
    for i in (0, 7):
        np.testing.assert_array_equal(joined[i].color, sample[i].color)
        np.testing.assert_array_equal(joined[i].depth, sample[i].depth)


def test_concatenate_rejects_frames_of_another_size_or_intrinsic(sample):
    with pytest.raises(InputError, match="160x120.*do not match.*320x240"):
        concatenate([sample[FIRST], sample[REST].at_scale(0.5)])
    other = synthetic_sequence(3, 320, 240).sequence
    with pytest.raises(InputError, match="intrinsic"):
        concatenate([sample[FIRST], other])


# -- a field that grows ---------------------------------------------------------------------------
def small_field(box):
    torch.manual_seed(0)
    return HashGridConfig(levels=4, log2_table_size=12, max_resolution=64).build(torch.tensor(box, dtype=torch.float32))


def test_a_grown_field_encodes_its_old_box_as_before_and_the_rest_with_the_new_block():
    """A grown field re-normalises a point into its old block's box: exactly as before where that
    arithmetic is exact (boxes of power-of-two sizes, points on a dyadic grid: every coordinate
    comes back bit for bit), within the rounding of the re-normalisation elsewhere (a point on a
    cell boundary may round into the neighbouring cell: the encoding is continuous there, so the
    change is a few ulps of the coordinate times the field's slope)."""
    old_box, new_box = [[0, 0, 0], [1, 1, 1]], [[-1, 0, 0], [3, 1, 2]]
    field = small_field(old_box)
    with torch.no_grad():  # a trained-looking field: features far from their initial 1e-4
        for p in field.encoding.parameters():
            p.normal_()
    dyadic = (torch.randint(1, 1023, (500, 3)) + 0.5) / 1024  # exact in float32, and so is (x + 1) / 4 * 4 - 1
    anywhere = torch.rand(500, 3) * 0.98 + 0.01
    outside = torch.rand(500, 3) * torch.tensor([4.0, 1, 2]) + torch.tensor([-1.0, 0, 0])
    outside = outside[(outside[:, 0] < 0) | (outside[:, 0] > 1) | (outside[:, 2] > 1)]
    before = [field.geometry(x) for x in (dyadic, anywhere)]
    grow(field, new_box, small_field(new_box).encoding)
    assert isinstance(field.encoding, BlockEncoding) and len(field.encoding.blocks) == 2
    np.testing.assert_allclose(field.aabb.numpy(), new_box)
    (sigma, features), (sigma_any, features_any) = (field.geometry(x) for x in (dyadic, anywhere))
    assert torch.equal(sigma, before[0][0]) and torch.equal(features, before[0][1])
    torch.testing.assert_close(sigma_any, before[1][0], rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(features_any, before[1][1], rtol=1e-3, atol=1e-3)
    old_block, new_block = field.encoding.blocks
    field.density(outside).sum().backward()  # points outside the old box train the new block only
    assert all(p.grad is None or not p.grad.any() for p in old_block.parameters())
    assert any(p.grad is not None and p.grad.any() for p in new_block.parameters())
    assert (field.density(outside) > 0).all()  # represented: no longer outside the field's box
    assert block_boxes(field) == [old_box, new_box]
    with pytest.raises(ValueError, match="does not hold"):
        grow(field, old_box, small_field(old_box).encoding)


def test_a_grown_blocks_table_holds_the_volume_it_adds_at_the_first_blocks_rows_per_cell():
    unit = [[0, 0, 0], [1, 1, 1]]
    assert block_table_size(19, unit, [[0, 0, 0], [2, 1, 1]]) == 18  # adds half the box: half the rows
    assert block_table_size(19, unit, [[0, 0, 0], [2, 2, 2]]) == 19  # 7/8 of the box: rounded up, 2^19
    assert block_table_size(19, [[0, 0, 0], [19, 1, 1]], [[0, 0, 0], [23, 1, 1]]) == 17  # 4/23 -> 2^16.5 -> 2^17
    assert block_table_size(19, unit, [[0, 0, 0], [1.000001, 1, 1]]) == 4  # a sliver: the smallest table
    assert block_table_size(12, unit, [[-9, -9, -9], [9, 9, 9]]) == 12  # never more rows than the field's


def test_a_field_grown_twice_builds_again_from_its_boxes_with_the_same_weights():
    boxes = [[[0, 0, 0], [1, 1, 1]], [[-1, 0, 0], [2, 1, 1]], [[-1, -1, 0], [2, 1, 1]]]
    config = ReconstructionConfig.preset("test", **{"hashgrid.levels": 4, "hashgrid.log2_table_size": 12,
                                                    "hashgrid.max_resolution": 64, "runtime.bf16_mlp": False})
    field = config.build_field(boxes[0])
    for box in boxes[1:]:
        config.grow_field(field, box)
    assert len(field.encoding.blocks) == 3  # one block per growth, not nested
    assert block_tables(field) == [12, 12, 11]  # the last growth adds 1/3 of its box: 2^(12 - 1.58) -> 2^11
    assert field.encoding.blocks[2].table.shape[0] == 4 * 2**11  # 4 levels (16..64 cells), all hashed
    rebuilt = config.build_field(boxes[-1], blocks=boxes)
    rebuilt.load_state_dict(field.state_dict())
    x = torch.rand(300, 3) * torch.tensor([3.0, 2, 1]) + torch.tensor([-1.0, -1, 0])
    torch.testing.assert_close(rebuilt.density(x), field.density(x))
    full = config.build_field(boxes[-1], blocks=boxes, tables=[12, 12, 12])  # as folders written before sizing
    assert block_tables(full) == [12, 12, 12]


def test_only_a_grid_field_grows():
    config = ReconstructionConfig.preset("test", field="vanilla")
    with pytest.raises(ConfigError, match="only a grid field can grow"):
        config.build_field([[-1, 0, 0], [1, 1, 1]], blocks=[[[0, 0, 0], [1, 1, 1]], [[-1, 0, 0], [1, 1, 1]]])


# -- tracking onto a map ----------------------------------------------------------------------------
@pytest.mark.slow
def test_tracking_onto_a_map_places_the_new_frames_as_tracking_them_all_at_once_does(sample):
    whole = track(sample, progress=False)
    first = track(sample[FIRST], progress=False)
    onto = track_onto(concatenate([sample[FIRST], sample[REST]]), first.poses, first.covariances, progress=False)
    np.testing.assert_allclose(onto.poses[:6], first.poses, atol=1e-9)  # the map stays where it is
    np.testing.assert_allclose(onto.covariances[:6], first.covariances)
    new = absolute_trajectory_error(onto.poses[6:], sample.gt_poses[6:])["rmse"]
    assert new <= absolute_trajectory_error(whole.poses[6:], sample.gt_poses[6:])["rmse"] + 1e-3
    placed = [e for e in onto.edges if e.target == 6 and e.success]
    assert placed and placed[0].source < 6  # from the map, not from identity
    # the map frame's own uncertainty is carried to the new frames: never below it
    sd = np.sqrt(np.diagonal(onto.covariances, axis1=1, axis2=2))
    assert (sd[6:] >= sd[placed[0].source] - 1e-9).all() and (sd[7:] > 0).all()


@pytest.mark.slow
def test_frames_that_do_not_overlap_the_map_raise_and_are_never_chained_from_a_guess(sample):
    first = track(sample[FIRST], progress=False)
    room = synthetic_sequence(3, 320, 240).sequence
    elsewhere = o3d.camera.PinholeCameraIntrinsic(sample.intrinsic)
    foreign = type(sample).from_rgbd_images([(f.color, f.depth) for f in room], elsewhere)
    with pytest.raises(TrackingError, match="first new frame, registers to none of the map's frames"):
        track_onto(concatenate([sample[FIRST], foreign]), first.poses, first.covariances, progress=False)


# -- Reconstruction.extend ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def first_map(sample, tmp_path_factory):
    cfg = ReconstructionConfig.preset("test", holdout_every=4, progress=False)
    recon = reconstruct(sample[FIRST], cfg, poses=sample.gt_poses[FIRST])
    return recon, recon.save(tmp_path_factory.mktemp("map") / "first")


@pytest.mark.slow
def test_extend_adds_the_frames_and_leaves_the_map_as_it_was(sample, first_map):
    base, folder = first_map
    weights = {k: v.clone() for k, v in base.field.state_dict().items()}
    poses = base.poses.copy()
    loaded = Reconstruction.load(folder)
    assert len(loaded.frames) == 6
    extended = loaded.extend(sample[REST], poses=sample.gt_poses[REST])
    assert len(extended.poses) == 11 and len(extended.frames) == 11
    np.testing.assert_array_equal(extended.train_indices, [1, 2, 3, 5, 7, 8, 9])
    np.testing.assert_array_equal(extended.holdout_indices, [0, 4, 6, 10])
    np.testing.assert_allclose(extended.poses, sample.gt_poses)
    steps, lr = round(0.5 * base.config.max_steps), base.config.optimizer.lr
    assert extended.stats["extended"] == [{"frames_before": 6, "frames_added": 5, "box_grown": False,
                                           "max_steps": steps, "lr": lr}]  # the default budget and rate
    assert extended.stats["training"]["steps"] == steps
    assert extended.config == base.config  # the map's own schedule: the next extension's default is the same
    assert extended.mesh is not None and len(extended.mesh.triangles) > 0
    for key, value in base.field.state_dict().items():  # the map extended is untouched
        torch.testing.assert_close(value, weights[key])
    np.testing.assert_array_equal(base.poses, poses)
    np.testing.assert_array_equal(extended.frames[8].depth, sample[8].depth)


@pytest.mark.slow
def test_an_extended_folder_extends_again_and_a_far_segment_grows_the_box(sample, first_map, tmp_path):
    base, folder = first_map
    once = Reconstruction.load(folder).extend(sample[6:9], poses=sample.gt_poses[6:9])
    once = Reconstruction.load(once.save(tmp_path / "once"))
    shifted = sample.gt_poses[9:11].copy()
    shifted[:, 0, 3] += 3.0  # the same images 3 m away: surfaces outside the box
    twice = once.extend(sample[9:11], poses=shifted)
    assert twice.stats["extended"][-1]["box_grown"] and len(twice.stats["extended"]) == 2
    schedules = [(e["max_steps"], e["lr"]) for e in twice.stats["extended"]]
    assert schedules[0] == schedules[1] == (round(0.5 * base.config.max_steps), base.config.optimizer.lr)
    assert twice.aabb[1, 0] > base.aabb[1, 0] + 2.5
    assert isinstance(twice.field.encoding, BlockEncoding)
    again = Reconstruction.load(twice.save(tmp_path / "twice"))
    np.testing.assert_allclose(again.aabb, twice.aabb)
    assert block_tables(again.field) == block_tables(twice.field)
    assert block_tables(twice.field)[-1] < twice.config.hashgrid.log2_table_size  # sized to the added volume
    out, expected = again.render(again.poses[1]), twice.render(twice.poses[1])
    np.testing.assert_allclose(out["depth"], expected["depth"], rtol=1e-5, atol=1e-5)

    # a folder written before grown blocks were sized (every block at the config's table size, and no
    # block_tables in its metadata) loads with the tables it was written with
    boxes, size = block_boxes(twice.field), twice.config.hashgrid.log2_table_size
    full = twice.config.build_field(twice.aabb, blocks=boxes, tables=[size] * len(boxes))
    twice.model.field = full
    legacy = twice.save(tmp_path / "legacy")
    meta = json.loads((legacy / "reconstruction.json").read_text())
    del meta["block_tables"]
    (legacy / "reconstruction.json").write_text(json.dumps(meta))
    assert block_tables(Reconstruction.load(legacy).field) == [size] * len(boxes)
    meta["block_tables"] = [size]  # one size for three blocks
    (legacy / "reconstruction.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="malformed metadata.*block_tables"):
        Reconstruction.load(legacy)


@pytest.mark.slow
def test_extend_rejects_bad_input_before_any_work(sample, first_map, tmp_path):
    base, folder = first_map
    with pytest.raises(InputError, match="do not match"):
        base.extend(sample[REST].at_scale(0.5))
    with pytest.raises(ConfigError, match="changes the map's field"):
        base.extend(sample[REST], config=base.config.replace(field="grid"))
    with pytest.raises(ConfigError, match="changes the map's field"):
        base.extend(sample[REST], config=base.config.replace(**{"hashgrid.levels": 4}))
    bare = Reconstruction.load(base.save(tmp_path / "bare", frames=False))
    assert bare.frames is None and not (tmp_path / "bare" / "frames").exists()
    with pytest.raises(InputError, match="does not keep the frames"):
        bare.extend(sample[REST])
    with pytest.raises(CheckpointError, match="not a saved reconstruction"):
        Reconstruction.load(tmp_path)


@pytest.mark.slow
def test_saved_frames_that_do_not_match_the_reconstruction_are_refused(first_map, tmp_path):
    import shutil

    base, folder = first_map
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    (copy / "frames" / "color" / "000005.png").unlink()
    with pytest.raises(CheckpointError, match="frames"):
        Reconstruction.load(copy)


@pytest.mark.slow
def test_cli_extend_writes_an_extended_folder_and_leaves_the_map(first_map, tmp_path, capsys):
    base, folder = first_map
    before = sorted(p.name for p in folder.iterdir())
    out = tmp_path / "extended"
    assert main(["--quiet", "extend", str(folder), "sample", "--frames", "6:11", "--gt-poses", "--out", str(out),
                 "--max-steps", "5"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 11 and report["training"]["steps"] == 5
    assert {"mesh.ply", "frames", "report.md", "tsdf_mesh.ply"} <= {p.name for p in out.iterdir()}
    assert sorted(p.name for p in folder.iterdir()) == before
    assert main(["--quiet", "evaluate", str(out), "--no-tsdf"]) == 0  # on the frames saved with it
    scores = json.loads((out / "evaluation.json").read_text())
    assert scores["holdout_frames"] == [0, 4, 6, 10]
    assert main(["--quiet", "extend", str(tmp_path), "sample", "--out", str(tmp_path / "x")]) == EXIT_ERROR
    assert "reconstruction.json" in capsys.readouterr().err

"""NeuS hash-grid field: encoding gradients, training on a small simulated session, cancel/resume, divergence,
pretraining to an initial SDF, save/load, the smoothness loss. CPU, "tiny" preset; asserts outcomes, never times."""

import signal
import threading
from dataclasses import replace

import numpy as np
import pytest
import torch
from torch.nn import functional

from n2d_common.config import load_config
from n2d_common.errors import Cancelled, ConfigError, N2DError
from n2d_common.torch_utils import load_checkpoint
from n2d_reconstruct.data import load_session
from n2d_reconstruct.neus import NeusConfig, NeusField, train_neus
from n2d_reconstruct.neus.encoding import HashGrid
from n2d_reconstruct.neus.field import NeusNetwork, frontal_views
from n2d_reconstruct.neus.renderer import RayOutput
from n2d_reconstruct.neus.trainer import _smoothness
from n2d_sim.session import render_session, small_world

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

BOX_HALF_M = np.array([0.045, 0.03, 0.07])
"""Half extents of the simulator's box (90 x 60 x 140 mm)."""
PSNR_FLOOR_DB = 17.0
"""Held-out PSNR on the mask the tiny preset must beat after its 300 steps (it reaches ~21 dB here)."""


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A 160x120 box session of 12 views (2 held out), its box in the turntable frame and the object pose."""
    out = tmp_path_factory.mktemp("neus") / "box"
    gt = render_session(out, small_world("box", 160, 120), views=12)
    data = load_session(out, holdout_every=6)
    centre = gt.T_turntable_obj[:3, 3] + gt.T_turntable_obj[:3, :3] @ np.array([0.0, 0.0, BOX_HALF_M[2]])
    reach = np.abs(gt.T_turntable_obj[:3, :3]) @ BOX_HALF_M + 0.01
    aabb = np.stack([centre - reach, centre + reach])
    aabb[0, 2] = 0.0
    return data, aabb, gt.T_turntable_obj


def box_sdf(points, T_turntable_obj):
    """Analytic signed distance (metres) of the simulator's box standing at its pose."""
    R, t = T_turntable_obj[:3, :3], T_turntable_obj[:3, 3]
    local = (points - t) @ R - np.array([0.0, 0.0, BOX_HALF_M[2]])
    q = np.abs(local) - BOX_HALF_M
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)


@pytest.fixture(scope="module")
def trained(session, tmp_path_factory):
    data, aabb, _ = session
    reports = []
    workdir = tmp_path_factory.mktemp("neus_train")
    field = train_neus(data.train, aabb, NeusConfig.preset("tiny"), workdir=workdir, progress=reports.append)
    return field, reports, workdir


def test_hash_grid_jacobian_and_table_gradient_match_autograd():
    torch.manual_seed(0)
    grid = HashGrid(levels=6, features=2, log2_table=10, base_res=4, max_res=100).double()
    grid.table.data.normal_()
    x = torch.rand(30, 3, dtype=torch.float64) * 0.98 + 0.01
    enc, jac = grid(x, jacobian=True)
    eye = torch.eye(3, dtype=torch.float64) * 1e-6
    numeric = torch.stack([(grid(x + eye[d])[0] - grid(x - eye[d])[0]) / 2e-6 for d in range(3)])
    assert torch.allclose(jac.permute(0, 2, 1), numeric, atol=1e-3 * float(jac.detach().abs().max()))
    # the table gradient of (enc, contracted jacobian) against plain autograd through table[idx]
    v = torch.randn_like(enc)
    ((enc * v).sum() + HashGrid.contract(jac, v).square().sum()).backward()
    mine = grid.table.grad.clone()
    grid.table.grad = None
    xr = x.clone().requires_grad_(True)
    pos = xr[:, None, :] * grid.res[None, :, None].double()
    cell = pos.detach().floor()
    frac = pos - cell
    ref = 0.0
    for corner in np.ndindex(2, 2, 2):
        c = cell.long() + torch.tensor(corner)
        mult = grid.mult.T.long()
        rows = (c[..., 0] * mult[:, 0]) ^ (c[..., 1] * mult[:, 1]) ^ (c[..., 2] * mult[:, 2])
        rows = (rows & (grid.table_size - 1)) + torch.arange(grid.levels) * grid.table_size
        w = torch.ones_like(frac[..., 0])
        for d in range(3):
            w = w * (frac[..., d] if corner[d] else 1 - frac[..., d])
        ref = ref + w[..., None] * grid.table[rows]
    ref = ref.reshape(len(x), -1)
    ref_jac = torch.autograd.grad((ref * v).sum(), xr, create_graph=True)[0]
    ((ref * v).sum() + ref_jac.square().sum()).backward()
    assert torch.allclose(enc, ref)
    assert torch.allclose(mine, grid.table.grad, atol=1e-6 * float(mine.abs().max()))


def test_training_reduces_the_loss_and_finds_the_object(session, trained):
    data, aabb, T_obj = session
    field, reports, workdir = trained
    losses = [r.info["loss"] for r in reports if np.isfinite(r.info.get("loss", np.nan))]
    assert np.mean(losses[-3:]) < 0.6 * np.mean(losses[:3])
    assert reports[-1].fraction == 1.0 and reports[-1].stage == "neus"
    assert reports[-1].message.startswith("step 300/300 loss ")
    assert {"step", "steps", "loss", "psnr"} <= set(reports[-1].info)
    centre = T_obj[:3, 3] + np.array([0.0, 0.0, BOX_HALF_M[2]])
    inside = field.sdf(centre[None])[0]
    assert inside < -0.01, "the SDF is not negative at the object's centre"
    corners = np.array([[x, y, 0.01] for x in aabb[:, 0] for y in aabb[:, 1]]) * [0.9, 0.9, 1.0]
    rim = np.array([[0.15 * np.cos(a), 0.15 * np.sin(a), 0.01] for a in np.linspace(0, 2 * np.pi, 8)])
    assert (field.sdf(corners) > 0).all(), "free space inside the box near the plate is not outside"
    assert (field.sdf(rim) > 0).all()
    assert (workdir / "neus.pt").is_file()


def test_rendered_held_out_view_resembles_the_photo(session, trained):
    data, _, _ = session
    field = trained[0]
    view = data.heldout
    mask = view.masks[0]
    image = field.render(view.K, view.T_turntable_cam[0], view.width, view.height, pixel_mask=mask)
    assert image.shape == (view.height, view.width, 3) and image.dtype == np.float32
    assert (image[~mask] == 0).all()
    mse = np.mean((image[mask] - view.rgb[0][mask] / 255.0) ** 2)
    psnr = -10 * np.log10(mse)
    assert psnr > PSNR_FLOOR_DB, f"held-out PSNR {psnr:.1f} dB"
    full = field.render(view.K, view.T_turntable_cam[0], view.width, view.height)
    np.testing.assert_allclose(full[mask], image[mask], atol=1e-5)


def test_save_load_and_albedo(trained, tmp_path):
    field = trained[0]
    field.save(tmp_path / "field.pt")
    loaded = NeusField.load(tmp_path / "field.pt")
    points = np.random.default_rng(0).uniform(field.aabb[0], field.aabb[1], (100, 3))
    np.testing.assert_allclose(loaded.sdf(points), field.sdf(points), atol=1e-6)
    normals = np.tile([0.0, 0.0, 1.0], (100, 1))
    albedo = loaded.albedo(points, normals)
    assert albedo.shape == (100, 3) and (albedo >= 0).all() and (albedo <= 1).all()
    # seen from training cameras: one camera straight out along each normal gives the along-the-normal colour
    eyes = np.array([[0.0, 0.0, 1e4], [5.0, 0.0, 0.0]])
    np.testing.assert_allclose(loaded.albedo(points, normals, eyes, k=1), albedo, atol=1e-4)
    blended = loaded.albedo(points, normals, eyes + [[0.3, 0.0, 0.0], [0.0, 0.0, 0.0]], k=2)
    assert blended.shape == (100, 3) and (blended >= 0).all() and (blended <= 1).all()
    checkpoint = NeusField.load(trained[2] / "neus.pt")  # a training checkpoint loads as a field too
    np.testing.assert_allclose(checkpoint.sdf(points), field.sdf(points), atol=1e-6)


def test_frontal_views_pick_the_most_frontal_cameras_and_fall_back_to_the_normal():
    points = np.zeros((2, 3))
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    eyes = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    dirs, weights = frontal_views(points, normals, eyes, k=2, sharpness=6.0, min_cos=0.15)
    np.testing.assert_allclose(dirs[0], [[-1.0, 0.0, 0.0], [-np.sqrt(0.5), -np.sqrt(0.5), 0.0]], atol=1e-12)
    np.testing.assert_allclose(weights[0], [1.0, np.sqrt(0.5) ** 6], atol=1e-12)
    # no camera sees the underside: it is seen along its normal alone
    np.testing.assert_allclose(dirs[1, 0], [0.0, 0.0, 1.0])
    np.testing.assert_allclose(weights[1], [1.0, 0.0])


def test_along_ray_meets_the_surface_and_keeps_a_grazing_ray_on_it():
    """A ray towards the (untrained, roughly spherical) surface reaches it; a ray tangent to it from a point
    just outside would step off along the tangent, so it keeps its start."""
    torch.manual_seed(0)
    cfg = NeusConfig.preset("tiny")
    net = NeusNetwork(cfg.field)
    field = NeusField(net, np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), cfg.render_spec(), "cpu")
    with torch.no_grad():  # the first point on the +x axis 0.08 outside the surface (within the steps' reach)
        axis = torch.linspace(0.0, 1.0, 201)[:, None] * torch.tensor([[1.0, 0.0, 0.0]])
        outside = axis[int(torch.nonzero(net.sdf(axis) > 0.08)[0, 0])][None]
    hit = field._along_ray(outside, torch.tensor([[-1.0, 0.0, 0.0]]))
    assert abs(float(hit.sdf[0].detach())) < 1e-3 and float(hit.x[0, 0].detach()) < float(outside[0, 0]) - 0.05
    normal = functional.normalize(hit.grad.detach(), dim=-1)
    start = hit.x.detach() + 0.004 * normal  # a mesh vertex a little off the field's surface
    tangent = functional.normalize(torch.linalg.cross(normal, torch.tensor([[0.0, 0.0, 1.0]])), dim=-1)
    stepped = field._along_ray(start, tangent, tolerance=float("inf"))
    assert abs(float(stepped.sdf[0].detach())) > 0.005  # unguarded, the steps leave the surface
    kept = field._along_ray(start, tangent)
    assert torch.equal(kept.x, start)


def test_cancel_saves_and_a_rerun_resumes_from_that_step(session, tmp_path):
    data, aabb, _ = session
    cfg = replace(NeusConfig.preset("tiny"), steps=60, checkpoint_every=1000)
    cancel = threading.Event()

    def stop_at_20(p):
        if p.info.get("step", 0) >= 20:
            cancel.set()

    with pytest.raises(Cancelled) as raised:
        train_neus(data.train, aabb, cfg, workdir=tmp_path, progress=stop_at_20, cancel=cancel)
    assert "resume from step 20" in raised.value.hint
    assert load_checkpoint(tmp_path / "neus.pt")["step"] == 20
    reports = []
    train_neus(data.train, aabb, cfg, workdir=tmp_path, progress=reports.append)
    assert reports[0].info["step"] == 20 and reports[0].message == "starting at step 20/60"
    assert [r.info["step"] for r in reports[1:]] == [30, 40, 50, 60]
    assert load_checkpoint(tmp_path / "neus.pt")["step"] == 60
    # another configuration does not resume that checkpoint
    reports.clear()
    train_neus(data.train, aabb, replace(cfg, steps=10), workdir=tmp_path, progress=reports.append)
    assert reports[0].info["step"] == 0


def test_divergence_raises_a_clear_error(session, tmp_path):
    data, aabb, _ = session
    cfg = NeusConfig.preset("tiny")
    cfg = replace(cfg, optim=replace(cfg.optim, lr=1e30, warmup_steps=1), steps=20)
    with pytest.raises(N2DError, match="NeuS training diverged at step") as raised:
        train_neus(data.train, aabb, cfg, workdir=tmp_path)
    assert "learning rate" in raised.value.hint


def test_pretraining_fits_the_initial_sdf(session, tmp_path):
    data, aabb, T_obj = session
    cfg = NeusConfig.preset("tiny")
    cfg = replace(cfg, steps=0, pretrain=replace(cfg.pretrain, steps=150))
    field = train_neus(data.train, aabb, cfg, workdir=tmp_path, init_sdf=lambda p: box_sdf(p, T_obj))
    points = np.random.default_rng(1).uniform(aabb[0], aabb[1], (4000, 3))
    truth = box_sdf(points, T_obj)
    near = np.abs(truth) < 0.005
    error = np.abs(field.sdf(points) - truth)
    assert np.median(error[near]) < 0.002, f"median error near the surface {np.median(error[near]) * 1000:.1f} mm"
    assert np.mean(np.sign(field.sdf(points[~near])) == np.sign(truth[~near])) > 0.98


def test_unknown_preset_is_an_error():
    with pytest.raises(N2DError, match="unknown NeuS preset"):
        NeusConfig.preset("huge")
    rays = [NeusConfig.preset(name).sampler.rays for name in ("gpu", "cpu", "tiny")]
    assert rays == sorted(rays, reverse=True) and len(set(rays)) == 3


def test_presets_fill_their_sections_and_keep_the_defaults_elsewhere():
    """A preset names only what it changes, section by section; the rest are the sections' defaults."""
    tiny, cpu, gpu = (NeusConfig.preset(name) for name in ("tiny", "cpu", "gpu"))
    assert (tiny.steps, tiny.field.levels, tiny.field.log2_table, tiny.sampler.rays, tiny.optim.warmup_steps,
            tiny.pretrain.points, tiny.checkpoint_every) == (300, 8, 14, 256, 20, 2048, 100)
    assert (tiny.field.colour_max_res, tiny.optim.lr, tiny.appearance.steps, tiny.loss.smooth_weight) == (
        2048, 1e-2, 0, 0.0)
    assert (cpu.steps, cpu.field.log2_table, cpu.appearance.steps, cpu.loss.smooth_edge_deg, cpu.pretrain.steps) == (
        6000, 18, 1500, 30.0, 300)
    assert (gpu.steps, gpu.field.max_res, gpu.sampler.coarse_every, gpu.sampler.coarse_samples,
            gpu.optim.cos_anneal_steps, gpu.pretrain.points) == (20000, 2048, 1, 64, 5000, 65536)
    assert cpu.render_spec().coarse_samples == 32 and not hasattr(cpu.render_spec(), "rays")


@pytest.mark.parametrize("override, message", [
    ("loss.smooth_weight=-0.01", "loss: smooth_weight must be a finite number >= 0"),
    ("optim.lr=nan", "optim: lr must be a finite number > 0"),
    ("sampler.rays=0", "sampler: rays must be a finite number > 0"),
    ("sampler.coarse_every=0", "coarse_every must be a finite number > 0"),
    ("appearance.samples=0", "samples must be a finite number > 0"),
    ("pretrain.steps=-1", "steps must be a finite number >= 0"),
    ("checkpoint_every=0", "checkpoint_every must be a finite number > 0"),
    ("field.max_res=8", "max_res must be >= base_res"),
    ("field.init_radius=1", "init_radius must be < 1"),
    ("sampler.background_fraction=1", "background_fraction must be in"),
    ("optim.lr_final_factor=2", "lr_final_factor must be in"),
    ("loss.smooth_edge_deg=200", "smooth_edge_deg must be in"),
    ("lr=0.1", "unknown key"),
    ("device=tpu", "device 'tpu'"),
])
def test_bad_neus_config_is_refused_at_the_boundary(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(NeusConfig, overrides=[override], base=NeusConfig.preset("cpu"))


def test_smoothness_measures_the_surface_curvature_and_trains_the_sdf_network():
    """On the initial sphere (radius R) the normals e ~ N(0, r) apart differ by |tangential e| / R: mean
    r sqrt(pi / 2) / R. Its gradient reaches the SDF network's weights on the encoding (zero at the start, so
    the table itself gets none yet). Rays that reach no surface give no loss."""
    net = NeusNetwork(NeusConfig.preset("tiny").field)
    R, r, n = net.spec.init_radius, 0.02, 4096
    gen = torch.Generator().manual_seed(0)
    o = functional.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 0.9
    d = -o / 0.9
    out = RayOutput(torch.zeros(n, 3), torch.ones(n), torch.zeros(0, 3), torch.full((n,), 0.9 - R))
    hit = torch.ones(n, dtype=torch.bool)
    loss = _smoothness(net, o, d, out, hit, r)
    assert float(loss) == pytest.approx(r * np.sqrt(np.pi / 2) / R, rel=0.1)
    loss.backward()
    assert float(net.sdf_layers[0].weight.grad[:, 3:].abs().sum()) > 0
    missed = RayOutput(torch.zeros(n, 3), torch.zeros(n), torch.zeros(0, 3), torch.zeros(n))
    assert float(_smoothness(net, o, d, missed, hit, r)) == 0.0


def test_smoothness_leaves_edges_alone():
    """Pairs of normals further apart than smooth_edge_deg add a constant: on the initial sphere, pairs drawn 0.3
    apart (mostly beyond 1 degree) give the capped loss and almost no gradient; a 180 degree cap changes nothing."""
    net = NeusNetwork(NeusConfig.preset("tiny").field)
    R, r, n = net.spec.init_radius, 0.3, 4096
    gen = torch.Generator().manual_seed(1)
    o = functional.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 0.9
    out = RayOutput(torch.zeros(n, 3), torch.ones(n), torch.zeros(0, 3), torch.full((n,), 0.9 - R))
    hit = torch.ones(n, dtype=torch.bool)

    def loss_and_gradient(edge_deg):
        net.zero_grad()
        torch.manual_seed(2)
        loss = _smoothness(net, o, -o / 0.9, out, hit, r, edge_deg)
        loss.backward()
        return float(loss), float(net.sdf_layers[0].weight.grad.abs().sum())

    full, capped, uncapped = loss_and_gradient(0.0), loss_and_gradient(1.0), loss_and_gradient(180.0)
    assert uncapped == pytest.approx(full, rel=1e-6)
    assert capped[0] <= 2 * np.sin(np.radians(0.5)) + 1e-6
    assert capped[1] < 0.05 * full[1]


def test_training_applies_the_smoothness_loss(session, tmp_path):
    """The same seeded steps with and without the loss give different fields (each step reseeds, so only the
    loss's gradient tells them apart)."""
    data, aabb, _ = session
    cfg = replace(NeusConfig.preset("tiny"), steps=10)
    plain, smooth = (train_neus(data.train, aabb, replace(cfg, loss=replace(cfg.loss, smooth_weight=w)),
                                workdir=tmp_path / str(w)) for w in (0.0, 1.0))
    points = np.random.default_rng(2).uniform(aabb[0], aabb[1], (2000, 3))
    a, b = plain.sdf(points), smooth.sdf(points)
    assert np.isfinite(b).all() and np.abs(a - b).max() > 1e-4


def _weights(workdir) -> dict:
    return load_checkpoint(workdir / "neus.pt")["network"]


def _same_weights(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_ctrl_c_saves_the_steps_done_and_the_rerun_ends_as_an_uninterrupted_run(session, tmp_path):
    """SIGINT (Ctrl-C in the CLI) between checkpoints: the steps done are saved, the rerun starts there and ends
    with the uninterrupted run's weights."""
    data, aabb, _ = session
    cfg = replace(NeusConfig.preset("tiny"), steps=30, checkpoint_every=1000)

    def ctrl_c_at_20(p):
        if p.info.get("step", 0) >= 20:
            signal.raise_signal(signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        train_neus(data.train, aabb, cfg, workdir=tmp_path / "a", progress=ctrl_c_at_20)
    assert load_checkpoint(tmp_path / "a" / "neus.pt")["step"] == 20
    reports = []
    train_neus(data.train, aabb, cfg, workdir=tmp_path / "a", progress=reports.append)
    assert reports[0].message == "starting at step 20/30"
    train_neus(data.train, aabb, cfg, workdir=tmp_path / "b")
    assert _same_weights(_weights(tmp_path / "a"), _weights(tmp_path / "b"))


def test_a_kill_after_the_checkpoint_at_the_appearance_stage_resumes(session, tmp_path):
    """The checkpoint written as the NeuS steps end (the appearance stage not begun) resumes into the appearance
    stage: a run stopped without saving after it (a kill) ends with the uninterrupted run's weights."""
    data, aabb, _ = session
    cfg = replace(NeusConfig.preset("tiny"), steps=20, checkpoint_every=10,
                  appearance=replace(NeusConfig.preset("tiny").appearance, steps=10))

    def killed_at_25(p):
        if p.info.get("step", 0) >= 25:
            raise SystemExit("killed")  # no save: what kill -9 leaves

    with pytest.raises(SystemExit):
        train_neus(data.train, aabb, replace(cfg, progress_every=5), workdir=tmp_path / "a", progress=killed_at_25)
    assert load_checkpoint(tmp_path / "a" / "neus.pt")["step"] == 20
    train_neus(data.train, aabb, cfg, workdir=tmp_path / "a")
    train_neus(data.train, aabb, cfg, workdir=tmp_path / "b")
    assert _same_weights(_weights(tmp_path / "a"), _weights(tmp_path / "b"))

import math
from dataclasses import replace

import pytest
import torch

from o3dsoft.model import (
    EdgeLayer,
    Encoder,
    LiteralEdgeLayer,
    MultiplicityBatchNorm,
    NetConfig,
    RelativeEdgeLayer,
    SoftAlignNet,
    ball_query,
    count_parameters,
    gather_max,
    neighbour_multiplicity,
    overlap_labels,
    overlap_loss,
    registration_loss,
)

from .conftest import TINY


def _cloud(b=2, n=60, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 3, generator=g, dtype=dtype) * 2 - 1


def test_ball_query_self_first_radius_and_padding():
    pts = _cloud(n=80)
    idx = ball_query(pts, 8, 0.4)
    assert idx.shape == (2, 80, 8)
    assert torch.equal(idx[:, :, 0], torch.arange(80).expand(2, 80))
    d = torch.linalg.norm(torch.gather(pts.unsqueeze(1).expand(-1, 80, -1, -1), 2, idx.unsqueeze(-1).expand(-1, -1, -1, 3)) - pts.unsqueeze(2), dim=-1)
    assert (d <= 0.4 + 1e-9).all()  # every neighbour (or padding copy of the point) lies inside r
    # An isolated point has only itself: its neighbourhood is K copies of it.
    far = torch.cat([pts[:1], torch.tensor([[[50.0, 50, 50]]], dtype=pts.dtype)], dim=1)
    idx_far = ball_query(far, 8, 0.4)
    assert (idx_far[0, -1] == 80).all()


def test_ball_query_rejects_k_above_n():
    with pytest.raises(ValueError, match="exceeds the number of points"):
        ball_query(_cloud(n=5), 8, 0.3)


def test_multiplicity_sums_to_nk():
    idx = ball_query(_cloud(n=50), 6, 0.5)
    m = neighbour_multiplicity(idx, 50)
    assert torch.allclose(m.sum(dim=1), torch.full((2,), 300.0))


def test_gather_max_matches_naive_and_gradients():
    z = torch.randn(3, 40, 7, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 40, (3, 40, 5))
    naive = torch.stack([z[b][idx[b]].amax(dim=1) for b in range(3)])
    out = gather_max(z, idx)
    assert torch.equal(out, naive)
    g = torch.randn_like(out)
    (gz,) = torch.autograd.grad(out, z, g)
    (gz_naive,) = torch.autograd.grad(naive, z, g)
    assert torch.allclose(gz, gz_naive)


@pytest.mark.parametrize("channels", [7, 64, 150])
def test_scripted_gather_max_matches_naive_in_channel_blocks_or_not(channels):
    # TorchScript takes its own paths: one loop over K with gradients, channel blocks of 64
    # (150 = two whole blocks and a part) into reused buffers without.
    scripted = torch.jit.script(gather_max)
    z = torch.randn(2, 90, channels)
    idx = torch.randint(0, 90, (2, 90, 6))
    naive = torch.stack([z[b][idx[b]].amax(dim=1) for b in range(2)])
    with torch.no_grad():
        assert torch.equal(scripted(z, idx), naive)
    assert torch.equal(scripted(z.requires_grad_(), idx), naive)


def test_gather_at_once_path_matches_chunked_loops():
    # The path GPUs take, checked on the CPU against the chunked loops: values and arg-max slots
    # (no ties in random features; the slot picks the row the gradient flows to).
    from o3dsoft.model import _gather_argmax_rows, _gather_argmax_rows_at_once

    rows = torch.randn(700, 9, dtype=torch.float64)
    flat = torch.randint(0, 700, (700, 6))
    out_loop, slot_loop = _gather_argmax_rows(rows, flat, chunk=128)
    out_once, slot_once = _gather_argmax_rows_at_once(rows, flat)
    assert torch.equal(out_loop, out_once)
    assert torch.equal(slot_loop, slot_once)


@pytest.mark.parametrize("c_in,c_out,relative", [(3, 16, False), (16, 32, False), (3, 16, True)])
def test_fast_layer_equals_literal_conv2d_layer(c_in, c_out, relative):
    torch.manual_seed(0)
    lit = LiteralEdgeLayer(c_in, c_out, relative).double()
    fast = (RelativeEdgeLayer if relative else EdgeLayer)(c_in, c_out).double()
    with torch.no_grad():  # non-trivial BN affine parameters, including negative scales
        lit.bn.weight.uniform_(-1.5, 1.5)
        lit.bn.bias.uniform_(-0.5, 0.5)
    lit.load_into(fast)
    x = _cloud(b=3, n=70, dtype=torch.float64) if c_in == 3 else torch.randn(3, 70, c_in, dtype=torch.float64)
    idx = ball_query(_cloud(b=3, n=70), 10, 0.5)
    m = neighbour_multiplicity(idx, 70, torch.float64)
    x1 = x.clone().requires_grad_(True)
    x2 = x.clone().requires_grad_(True)
    for _ in range(2):  # two training steps: running statistics accumulate identically
        out_lit = lit(x1.transpose(1, 2), idx).transpose(1, 2)
        out_fast = fast(x2, idx, m)
    assert torch.allclose(out_lit, out_fast, atol=1e-5, rtol=0)
    g = torch.randn_like(out_lit)
    out_lit.backward(g)
    out_fast.backward(g)
    assert torch.allclose(x1.grad, x2.grad, atol=1e-5, rtol=0)
    assert torch.allclose(lit.conv.weight.grad[:, :, 0, 0], fast.linear.weight.grad, atol=1e-5, rtol=0)
    assert torch.allclose(lit.conv.bias.grad, fast.linear.bias.grad, atol=1e-5, rtol=0)
    assert torch.allclose(lit.bn.weight.grad, fast.bn.weight.grad, atol=1e-5, rtol=0)
    assert torch.allclose(lit.bn.bias.grad, fast.bn.bias.grad, atol=1e-5, rtol=0)
    assert torch.allclose(lit.bn.running_mean, fast.bn.running_mean, atol=1e-10)
    assert torch.allclose(lit.bn.running_var, fast.bn.running_var, atol=1e-10)
    assert int(lit.bn.num_batches_tracked) == int(fast.bn.num_batches_tracked) == 2
    lit.eval()
    fast.eval()
    assert torch.allclose(lit(x.transpose(1, 2), idx).transpose(1, 2), fast(x, idx, m), atol=1e-5, rtol=0)


def test_float32_fast_layer_agrees_with_literal():
    torch.manual_seed(1)
    lit, fast = LiteralEdgeLayer(3, 64), EdgeLayer(3, 64)
    lit.load_into(fast)
    x = _cloud(b=2, n=128, dtype=torch.float32)
    idx = ball_query(x, 16, 0.4)
    out_lit = lit(x.transpose(1, 2), idx).transpose(1, 2)
    out_fast = fast(x, idx, neighbour_multiplicity(idx, 128))
    assert torch.allclose(out_lit, out_fast, atol=1e-5, rtol=1e-5)


def test_parameter_counts():
    # One encoder: 238,976 conv + 2,432 BatchNorm parameters; plus the learnt temperature.
    assert count_parameters(Encoder((64, 128, 256, 256, 512))) == 241_408
    assert count_parameters(SoftAlignNet(NetConfig())) == 241_409
    assert count_parameters(SoftAlignNet(NetConfig(shared_encoder=False))) == 2 * 241_408 + 1
    assert count_parameters(SoftAlignNet(NetConfig(learn_temperature=False))) == 241_408


def test_scripted_model_equals_eager():
    torch.manual_seed(0)
    net = SoftAlignNet(TINY).eval()
    scripted = torch.jit.script(net)
    src, tgt = _cloud(n=64, dtype=torch.float32), _cloud(n=50, seed=1, dtype=torch.float32)
    for a, b in zip(net(src, tgt), scripted(src, tgt)):
        assert torch.allclose(a, b, atol=1e-6)
    # Without gradients the scripted encoder folds each BatchNorm into its linear map, which
    # rounds differently (descriptors within 1e-7 in float32); an untrained network's almost
    # uniform soft assignment magnifies that in R, so that path is compared in float64.
    net = net.double()
    scripted = torch.jit.script(net)
    with torch.no_grad():
        for a, b in zip(net(src.double(), tgt.double()), scripted(src.double(), tgt.double())):
            assert torch.allclose(a, b, atol=1e-9)


def test_exported_steps_with_a_shared_target_equal_forward():
    torch.manual_seed(0)
    scripted = torch.jit.script(SoftAlignNet(TINY).eval())
    src, tgt = _cloud(b=3, n=64, dtype=torch.float32), _cloud(b=1, n=50, seed=1, dtype=torch.float32)
    with torch.no_grad():
        g = scripted.describe_target(tgt, ball_query(tgt, TINY.k, TINY.radius))
        f = scripted.describe_source(src, ball_query(src, TINY.k, TINY.radius))
        assert g.shape == (1, 50, TINY.channels[-1]) and f.shape == (3, 64, TINY.channels[-1])
        for a, b in zip(scripted.align(src, f, tgt, g), scripted(src, tgt.expand(3, -1, -1))):
            assert torch.allclose(a, b, atol=1e-6)


def test_outputs_shapes_and_ranges():
    net = SoftAlignNet(TINY).eval()
    R, t, w = net(_cloud(n=64, dtype=torch.float32), _cloud(n=50, seed=1, dtype=torch.float32))
    assert R.shape == (2, 3, 3) and t.shape == (2, 3) and w.shape == (2, 64)
    assert torch.allclose(torch.det(R), torch.ones(2), atol=1e-5)
    assert ((w >= 1 / 50 - 1e-6) & (w <= 1 + 1e-6)).all()


@pytest.mark.parametrize("shared", [True, False])
def test_training_steps_reduce_loss_without_nan(shared):
    torch.manual_seed(0)
    net = SoftAlignNet(NetConfig(k=8, radius=0.3, channels=(16, 16, 32, 32, 32), shared_encoder=shared))
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    src = _cloud(b=4, n=64, dtype=torch.float32)
    c, s = torch.cos(torch.tensor(0.3)), torch.sin(torch.tensor(0.3))
    R_gt = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]]).expand(4, 3, 3)
    tgt = src @ R_gt.transpose(1, 2)
    t_gt = torch.zeros(4, 3)
    losses = []
    for _ in range(15):
        R, t, _ = net(src, tgt)
        loss = registration_loss(R, t, R_gt, t_gt)
        opt.zero_grad()
        loss.backward()
        assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.parametrize("relative", [False, True])
def test_fast_encoder_equals_literal_encoder(relative):
    from o3dsoft.model import LiteralEncoder

    torch.manual_seed(3)
    channels = (8, 16, 16, 16, 24)
    lit, fast = LiteralEncoder(channels, relative).double(), Encoder(channels, relative).double()
    lit.load_into(fast)
    pts = _cloud(b=2, n=90, dtype=torch.float64)
    idx = ball_query(pts, 12, 0.4)
    p1, p2 = pts.clone().requires_grad_(True), pts.clone().requires_grad_(True)
    out_lit, out_fast = lit(p1, idx), fast(p2, idx)
    assert torch.allclose(out_lit, out_fast, atol=1e-5, rtol=0)
    g = torch.randn_like(out_lit)
    out_lit.backward(g)
    out_fast.backward(g)
    assert torch.allclose(p1.grad, p2.grad, atol=1e-5, rtol=0)
    for a, b in zip(lit.layers, fast.layers):
        assert torch.allclose(a.conv.weight.grad[:, :, 0, 0], b.linear.weight.grad, atol=1e-5, rtol=0)


@pytest.mark.parametrize("relative", [False, True])
def test_scripted_inference_folds_batchnorm_and_equals_eager(relative):
    # Scripted, in eval mode, without gradients, on the CPU, the encoder folds each BatchNorm
    # into its linear map and runs it in blocks of 64 output channels (150 = two blocks and a
    # part); BatchNorm statistics and scales of either sign, so that the folding matters.
    torch.manual_seed(6)
    enc = Encoder((8, 70, 150, 16, 130), relative).double()
    for bn in (m for m in enc.modules() if isinstance(m, MultiplicityBatchNorm)):
        c = bn.weight.shape[0]
        with torch.no_grad():
            bn.weight.copy_(torch.randn(c, dtype=torch.float64))
            bn.bias.copy_(torch.randn(c, dtype=torch.float64))
        bn.running_mean.copy_(torch.randn(c))
        bn.running_var.copy_(torch.rand(c) + 0.1)
    enc.eval()
    scripted = torch.jit.script(enc)
    pts = _cloud(b=2, n=90, dtype=torch.float64)
    idx = ball_query(pts, 12, 0.4)
    eager = enc(pts, idx)
    assert (eager > 0).float().mean() > 0.2  # the folded BatchNorms do not leave everything at 0
    with torch.no_grad():
        assert torch.allclose(scripted(pts, idx), eager, atol=1e-9, rtol=0)
    assert torch.allclose(scripted(pts, idx), eager, atol=1e-9, rtol=0)  # with gradients: unfolded


@pytest.mark.parametrize("training", [False, True])
def test_relative_descriptors_do_not_depend_on_where_the_cloud_lies(training):
    # A cropped cloud's centroid moves with the crop; the relative first layer makes the
    # descriptors blind to that shift, in training (batch statistics) and at inference alike.
    torch.manual_seed(4)
    pts = _cloud(b=2, n=90, dtype=torch.float64)
    # One cloud of the batch moved: in training a shift of the whole batch would cancel in the
    # absolute form's batch statistics too.
    shift = torch.tensor([[[0.3, -0.2, 0.15]], [[0.0, 0.0, 0.0]]], dtype=torch.float64)
    idx = ball_query(pts, 12, 0.4)
    out = []
    for relative in (True, False):
        enc = Encoder((8, 16, 16, 16, 24), relative).double().train(training)
        out.append((enc(pts, idx), enc(pts + shift, idx)))
    assert torch.allclose(out[0][0], out[0][1], atol=1e-9)
    assert not torch.allclose(out[1][0], out[1][1], atol=1e-3)  # the absolute form does depend on it


def test_relative_network_scripts_and_round_trips_its_config():
    torch.manual_seed(5)
    config = NetConfig(k=8, radius=0.5, channels=(8, 16, 16, 16, 24), relative=True)
    assert NetConfig.from_dict(config.to_dict()) == config
    assert NetConfig.from_dict({k: v for k, v in config.to_dict().items() if k != "relative"}).relative is False
    net = SoftAlignNet(config).eval()
    src, tgt = _cloud(b=2, n=64, dtype=torch.float32), _cloud(b=2, n=64, seed=1, dtype=torch.float32)
    scripted = torch.jit.script(net)
    for a, b in zip(net(src, tgt), scripted(src, tgt)):
        assert torch.allclose(a, b, atol=1e-5)


def test_rescripting_a_model_file_keeps_its_weights_metadata_and_outputs(tiny_model_path, tmp_path):
    from o3dsoft.coarse import load_model, rescript

    old = load_model(tiny_model_path)
    new = load_model(rescript(old, tmp_path / "again.pt"))
    assert new.meta == old.meta
    src, tgt = _cloud(n=64, dtype=torch.float32), _cloud(n=50, seed=1, dtype=torch.float32)
    for a, b in zip(old.run(src, tgt), new.run(src, tgt)):
        assert torch.equal(a, b)


def test_a_rescripted_card_says_so_once_with_the_latest_difference():
    from benchmarks.rescript_model import rescripted_note

    note = rescripted_note("Trained on wide45.", 4e-6)
    assert note == (
        "Trained on wide45. Re-scripted with later inference code (benchmarks/rescript_model.py); same weights, outputs within 4e-06 of the previous file's."
    )
    for worst in (1e-4, 0.0):  # 1e-4 prints as 0.0001, whose dot must not end the sentence early
        again = rescripted_note(rescripted_note(note, worst), 2e-5)
        assert again.count("Re-scripted") == 1 and again.endswith("outputs within 2e-05 of the previous file's.")
        assert again.startswith("Trained on wide45. Re-scripted")
    assert rescripted_note("x.", 0.0).endswith("outputs identical to the previous file's.")


def test_virtual_point_loss_counts_only_points_with_a_partner():
    from o3dsoft.model import virtual_point_loss

    torch.manual_seed(0)
    source = torch.rand(2, 50, 3)
    R = torch.eye(3).expand(2, 3, 3)
    t = torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]])
    truth = source + t[:, None]
    assert virtual_point_loss(source, truth, truth, R, t).item() == 0.0  # every soft partner where it belongs
    off = truth + torch.tensor([0.0, 0.0, 0.1])
    assert virtual_point_loss(source, truth, off, R, t).item() == pytest.approx(0.01, rel=1e-5)  # 0.1 off each
    far_target = truth + 10.0  # nothing within reach of where the points lie: no partner, no loss
    assert virtual_point_loss(source, far_target, off, R, t).item() == 0.0


def test_match_loss_is_the_cross_entropy_of_the_mass_near_each_true_partner():
    from o3dsoft.model import match_loss

    torch.manual_seed(0)
    source = torch.rand(1, 30, 3) * 10.0  # points far apart: each has one target point within reach
    R = torch.eye(3)[None]
    t = torch.tensor([[0.5, 0.0, 0.0]])
    target = source + t[:, None]
    one_hot = torch.eye(30)[None]
    assert match_loss(source, target, one_hot, R, t).item() == pytest.approx(0.0, abs=1e-6)
    uniform = torch.full((1, 30, 30), 1 / 30)
    assert match_loss(source, target, uniform, R, t).item() == pytest.approx(math.log(30), rel=1e-5)
    shifted = torch.roll(one_hot, 1, dims=-1)  # all mass on a wrong point: the floor of 1e-12
    assert match_loss(source, target, shifted, R, t).item() == pytest.approx(-math.log(1e-12), rel=1e-4)
    far = target + 100.0  # no target point within reach of any true place: no partner, no loss
    assert match_loss(source, far, uniform, R, t).item() == 0.0


def test_partner_auc_is_one_where_the_weights_rank_every_point_with_a_partner_first():
    from benchmarks.soft_partners import partner_auc

    has = torch.arange(40)[None] < 20  # (1, 40): the first 20 points have a partner
    right = torch.where(has, 0.9, 0.01)
    assert partner_auc(right, has) == 1.0 and partner_auc(1.0 - right, has) == 0.0
    assert partner_auc(torch.full((1, 40), 0.5), has) == 0.5  # ties count half: chance
    both = torch.cat([right, 1.0 - right])  # two pairs: the median of 1 and 0
    assert partner_auc(both, has.expand(2, -1)) == 0.5
    assert partner_auc(right, torch.ones_like(has)) is None  # every point has a partner: no AUC


def test_the_network_keeps_its_soft_partners_when_eager_and_scripts_without_them():
    from o3dsoft.model import NetConfig, SoftAlignNet

    net = SoftAlignNet(NetConfig(k=8, channels=(8, 16))).eval()
    src, tgt = torch.rand(1, 40, 3), torch.rand(1, 30, 3)
    R, t, w = net(src, tgt)
    assert net.virtual_points.shape == (1, 40, 3) and net.soft_partners.shape == (1, 40, 30)
    R_s, t_s, w_s = torch.jit.script(net)(src, tgt)
    assert torch.allclose(R, R_s, atol=1e-5) and torch.allclose(t, t_s, atol=1e-5)


def test_an_export_does_not_carry_the_last_calls_soft_partners(tmp_path):
    """The training loop's last batch leaves B x N x M soft partners on the network; the exported
    file is as small after it as before any call."""
    from o3dsoft.coarse import export_torchscript, load_model
    from o3dsoft.model import NetConfig, SoftAlignNet

    config = NetConfig(k=8, channels=(8, 16), overlap=8)
    net = SoftAlignNet(config)
    fresh = export_torchscript(net, config, tmp_path / "fresh.pt").stat().st_size
    src, tgt = torch.rand(8, 512, 3), torch.rand(8, 512, 3)  # soft partners: 8 MiB
    R, t, w = net.eval()(src, tgt)
    after = export_torchscript(net, config, tmp_path / "after.pt").stat().st_size
    assert after < fresh + 10_000, (fresh, after)
    R_s, t_s, _ = load_model(tmp_path / "after.pt").module(src, tgt)
    assert torch.allclose(R, R_s, atol=1e-5) and torch.allclose(t, t_s, atol=1e-5)


def test_soft_partner_sharpness_is_one_for_uniform_weights_and_rises_as_the_temperature_falls(modelnet_root):
    from benchmarks.soft_partners import sharpness

    torch.manual_seed(0)
    net = SoftAlignNet(TINY)
    with torch.no_grad():
        net.log_tau.fill_(math.log(1e6))  # scores ~0: uniform rows
    flat = sharpness(net, str(modelnet_root), "incongruent", limit=2)
    assert flat["max_w_times_m"] == pytest.approx(1.0, abs=1e-3)
    assert flat["match_loss"] == pytest.approx(flat["uniform_match_loss"], rel=1e-3)
    with torch.no_grad():
        net.log_tau.fill_(math.log(1e-3))  # near one-hot rows
    sharp = sharpness(net, str(modelnet_root), "incongruent", limit=2)
    assert sharp["max_w_times_m"] > 2 * flat["max_w_times_m"] and sharp["positives_per_point"] == flat["positives_per_point"]
    assert flat["overlap_auc"] is None or flat["overlap_auc"] == pytest.approx(0.5)  # uniform rows: one weight for all
    assert flat["head_overlap_auc"] is None


def test_soft_partners_reports_an_overlap_heads_auc_for_both_clouds(modelnet_root):
    from benchmarks.soft_partners import sharpness

    torch.manual_seed(0)
    figures = sharpness(SoftAlignNet(_with_head()), str(modelnet_root), "incongruent-crop", limit=3)
    for key in ("overlap_auc", "head_overlap_auc", "head_target_overlap_auc"):
        assert 0.0 <= figures[key] <= 1.0


def _with_head(config=TINY, width=16):
    return replace(config, overlap=width)


def test_a_network_with_an_overlap_head_scripts_and_equals_eager_with_a_shared_target():
    torch.manual_seed(6)
    net = SoftAlignNet(_with_head()).double().eval()  # float64: see test_scripted_model_equals_eager
    assert NetConfig.from_dict(_with_head().to_dict()) == _with_head()
    src, tgt = _cloud(b=3, n=64), _cloud(b=1, n=50, seed=1)
    scripted = torch.jit.script(net)
    with torch.no_grad():
        g = scripted.describe_target(tgt, ball_query(tgt, TINY.k, TINY.radius))
        f = scripted.describe_source(src, ball_query(src, TINY.k, TINY.radius))
        for a, b in zip(net(src, tgt.expand(3, -1, -1)), scripted.align(src, f, tgt, g)):
            assert torch.allclose(a, b, atol=1e-9)
    assert [t.shape for t in net.overlap_logits] == [(3, 64), (3, 50)]


def test_an_overlap_head_that_says_the_same_of_every_point_changes_no_pose():
    torch.manual_seed(7)
    plain = SoftAlignNet(TINY).double().eval()
    headed = SoftAlignNet(_with_head()).double().eval()
    headed.load_state_dict(plain.state_dict(), strict=False)
    src, tgt = _cloud(n=64), _cloud(n=50, seed=1)
    readout = headed.overlap[0].readout
    with torch.no_grad():
        assert torch.allclose(plain(src, tgt)[0], headed(src, tgt)[0], atol=1e-9)  # a new head starts at zero
        for bias in (-3.0, 0.0, 4.0):  # a common column shift leaves each softmax row as it was
            readout.bias.fill_(bias)
            for a, b in zip(plain(src, tgt)[:2], headed(src, tgt)[:2]):
                assert torch.allclose(a, b, atol=1e-9)
        readout.weight.normal_()  # logits that differ between points change the pose
        assert not torch.allclose(plain(src, tgt)[0], headed(src, tgt)[0], atol=1e-4)


def test_overlap_labels_count_spacings_from_each_points_true_place():
    # Source x = 0..19 and target x = 10.5..29.5 on a line, spacing 1; the source given turned
    # and shifted, with the transform that puts it back. Within 3 spacings: source x >= 8, target x <= 21.5.
    R = torch.tensor(_rotation_about_z(0.7), dtype=torch.float64)
    t = torch.tensor([0.3, -2.0, 5.0], dtype=torch.float64)
    line = lambda xs: torch.stack([xs, torch.zeros_like(xs), torch.zeros_like(xs)], -1)  # noqa: E731
    placed, target = line(torch.arange(20.0).double()), line(torch.arange(20.0).double() + 10.5)
    source = (placed - t) @ R  # R^T (x - t), row-wise
    in_s, in_t = overlap_labels(source[None], target[None], R[None], t[None])
    assert in_s[0].tolist() == [x >= 8 for x in range(20)]
    assert in_t[0].tolist() == [x + 10.5 <= 21.5 for x in range(20)]
    narrow = overlap_labels(source[None], target[None], R[None], t[None], spacings=1.0)[0]
    assert narrow[0].tolist() == [x >= 10 for x in range(20)]


def test_the_overlap_loss_is_small_for_right_logits_and_large_for_reversed_ones():
    labels = (torch.tensor([[True, False, True]]), torch.tensor([[False, True]]))
    right = tuple(torch.where(y, 20.0, -20.0) for y in labels)
    reversed_ = tuple(-x for x in right)
    assert overlap_loss(right, labels) < 1e-6
    assert overlap_loss(reversed_, labels) == pytest.approx(40.0, rel=1e-6)  # 20 nats each, source and target
    unsure = tuple(torch.zeros(y.shape) for y in labels)
    assert overlap_loss(unsure, labels) == pytest.approx(2 * math.log(2), rel=1e-6)


def _rotation_about_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]


def test_soft_partners_measures_the_overlap_aucs_on_scans_at_the_true_pose(tmp_path):
    from benchmarks.soft_partners import scan_overlap_auc

    from .conftest import EXAMPLES

    (tmp_path / "pairs.txt").write_text(f"{EXAMPLES / 'bun045.ply'} {EXAMPLES / 'bun000.ply'} {EXAMPLES / 'bun045_to_bun000.txt'}\n")
    torch.manual_seed(0)
    net = SoftAlignNet(_with_head())
    untrained = scan_overlap_auc(net, tmp_path, points=128)
    assert untrained["pairs"] == 1 and untrained["points"] == 128
    # A head whose read-out is still zero gives every point one logit: chance, whatever the overlap.
    assert untrained["head_overlap_auc"] == pytest.approx(0.5) and untrained["head_target_overlap_auc"] == pytest.approx(0.5)
    with torch.no_grad():
        net.overlap[0].readout.weight.normal_()
    assert scan_overlap_auc(net, tmp_path, points=128)["head_overlap_auc"] != pytest.approx(0.5)
    assert scan_overlap_auc(SoftAlignNet(TINY), tmp_path, points=128)["head_overlap_auc"] is None


def test_a_trimmed_pass_keeping_every_point_is_the_networks_own_pass_with_a_silent_head():
    import numpy as np

    from benchmarks.network_from_truth import trimmed_pass

    torch.manual_seed(2)
    net = SoftAlignNet(_with_head()).eval()  # the head's read-out starts at zero: it changes no pose
    src, tgt = _cloud(b=1, n=64, dtype=torch.float32), _cloud(b=1, n=56, seed=1, dtype=torch.float32)
    src, tgt = src - src.mean(dim=1, keepdim=True), tgt - tgt.mean(dim=1, keepdim=True)  # the pass re-centres what it keeps
    with torch.no_grad():
        net.log_tau.fill_(-3.0)  # sharper rows: an untrained network's near-uniform ones make the rotation ill-conditioned
        R, _, _ = net(src, tgt)
    plain = SoftAlignNet(TINY).eval()
    plain.load_state_dict({name: w for name, w in net.state_dict().items() if not name.startswith("overlap.")})
    whole = trimmed_pass(net, plain, src[0].numpy(), tgt[0].numpy(), keep=1.0)
    assert np.allclose(whole, R[0].numpy(), atol=1e-4)
    with torch.no_grad():
        net.overlap[0].readout.weight.normal_()
    part = trimmed_pass(net, plain, src[0].numpy(), tgt[0].numpy(), keep=0.5)
    assert np.allclose(part @ part.T, np.eye(3), atol=1e-5) and not np.allclose(part, whole, atol=1e-3)

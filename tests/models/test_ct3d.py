"""CT3D: cylinder point gathering, keypoint encoding, channel-wise attention, the model end to end."""
import copy
import math

import numpy as np
import pytest
import torch

import models
from detbench.train.run_config import load_run_config
from models.stages.ct3d_head import (
    ChannelWiseAttention, ChannelWiseDecoderLayer, cylinder_radius, encode_proposal_points, gather_cylinder_points,
)
from tests.helpers import TINY, batch_of, box_points

def _tiny_ct3d() -> dict:
    """TINY (the tiny SECOND of tests/helpers.py) with the ct3d smoke preset's second stage, a few sizes smaller."""
    cfg = copy.deepcopy(load_run_config("ct3d", "smoke")["model"])
    cfg.update({k: copy.deepcopy(v) for k, v in TINY.items() if k != "name"})
    rh = cfg["roi_head"]
    rh.update({"fc": [32], "dropout": 0.0})
    rh["proposals"]["train"].update(pre_nms_top_k=200, post_nms_top_k=32)
    rh["proposals"]["test"].update(pre_nms_top_k=100, post_nms_top_k=16)
    rh["targets"].update(roi_per_image=16, gt_jitter_copies=2)
    return cfg


TINY_CT3D = _tiny_ct3d()


def random_scene(seed, n=400, r=6):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, 4, generator=g) * torch.tensor([12.0, 6.0, 3.0, 1.0]) - torch.tensor([0.0, 3.0, 0.0, 0.0])
    rois = torch.rand(r, 7, generator=g) * torch.tensor([12.0, 6.0, 2.0, 3.0, 1.5, 1.5, 6.28]) \
        + torch.tensor([0.0, -3.0, 0.0, 0.5, 0.3, 0.5, -3.14])
    return pts, rois


@pytest.mark.parametrize("random", [False, True])
def test_cylinder_gathering_matches_brute_force(random):
    pts, rois = random_scene(0)
    k = 12
    points = torch.cat([torch.zeros(len(pts), 1), pts], 1)
    rois = torch.cat([rois, torch.tensor([[100.0, 0.0, 1.0, 4.0, 1.8, 1.5, 0.0]])])  # far away: empty
    got = gather_cylinder_points(points, rois[None], k, radius_scale=1.2, random=random)
    rad = cylinder_radius(rois, 1.2)
    for j in range(len(rois)):
        d = torch.hypot(pts[:, 0] - rois[j, 0], pts[:, 1] - rois[j, 1])
        inside = pts[d <= rad[j]]
        assert int(got.count[0, j]) == len(inside)
        sample = got.points[0, j]
        if len(inside) == 0:
            assert bool(got.empty[0, j]) and torch.equal(sample, torch.zeros(k, 4))
            continue
        members = {tuple(p.tolist()) for p in inside}
        assert all(tuple(p.tolist()) in members for p in sample)  # every sampled point lies in the cylinder
        if len(inside) >= k:
            assert len({tuple(p.tolist()) for p in sample}) == k  # distinct points
        else:  # all inside points, then cyclic repetition
            assert {tuple(p.tolist()) for p in sample} == members
            assert torch.equal(sample[len(inside):], sample[:k - len(inside)])
    assert int(got.empty.sum()) >= 1


def test_gathering_is_deterministic_in_evaluation_and_seeded_in_training():
    pts, rois = random_scene(1, n=2000)
    points = torch.cat([torch.zeros(len(pts), 1), pts], 1)
    a = gather_cylinder_points(points, rois[None], 8, 1.2, random=False)
    b = gather_cylinder_points(points, rois[None], 8, 1.2, random=False)
    assert torch.equal(a.points, b.points)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    c = gather_cylinder_points(points, rois[None], 8, 1.2, random=True, generator=g1)
    d = gather_cylinder_points(points, rois[None], 8, 1.2, random=True, generator=g2)
    assert torch.equal(c.points, d.points) and not torch.equal(a.points, c.points)


def test_keypoint_encoding_is_invariant_to_a_rigid_motion():
    pts, rois = random_scene(2, n=64, r=4)
    samples = pts[None].expand(4, -1, -1)
    enc = encode_proposal_points(samples, rois)
    assert enc.shape == (4, 64, 28) and torch.isfinite(enc).all()
    theta, shift = 0.9, torch.tensor([30.0, -7.0, 0.0])
    c, s = math.cos(theta), math.sin(theta)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved_pts = samples.clone()
    moved_pts[..., :3] = samples[..., :3] @ rot.T + shift
    moved_rois = rois.clone()
    moved_rois[:, :3] = rois[:, :3] @ rot.T + shift
    moved_rois[:, 6] = rois[:, 6] + theta
    enc2 = encode_proposal_points(moved_pts, moved_rois)
    dist, az, incl, feat = enc[..., :9], enc[..., 9:18], enc[..., 18:27], enc[..., 27:]
    dist2, az2, incl2, feat2 = enc2[..., :9], enc2[..., 9:18], enc2[..., 18:27], enc2[..., 27:]
    assert torch.allclose(dist, dist2, atol=1e-4) and torch.allclose(incl, incl2, atol=1e-3)
    assert torch.allclose(torch.cos(az), torch.cos(az2), atol=1e-3) and torch.allclose(torch.sin(az), torch.sin(az2),
                                                                                       atol=1e-3)
    assert torch.equal(feat, feat2)
    # a point on a keypoint (distance 0) is still finite
    on = rois[:1, None, :3].clone()
    assert torch.isfinite(encode_proposal_points(torch.cat([on, torch.zeros(1, 1, 1)], -1), rois[:1])).all()


def test_channel_wise_weights_sum_to_one_over_points_per_channel():
    torch.manual_seed(0)
    attn = ChannelWiseAttention(16, 4)
    out, w = attn(torch.randn(5, 16), torch.randn(5, 9, 16))
    assert out.shape == (5, 16) and w.shape == (5, 4, 4, 9)
    assert torch.allclose(w.sum(dim=-1), torch.ones(5, 4, 4), atol=1e-6)
    # the weights differ between channels (not one weight per point as in plain attention)
    assert float((w[:, :, 0] - w[:, :, 1]).abs().max().detach()) > 1e-3


def test_channel_wise_decoder_equals_the_formula_by_hand():
    """The decoder layer on 3 RoIs x 5 points (d 8, 2 heads of 4), every sum written out in numpy."""
    rng = np.random.default_rng(7)
    layer = ChannelWiseDecoderLayer(8, 2, 12, dropout=0.0).double().eval()
    with torch.no_grad():
        for prm in layer.parameters():  # fixed weights, LayerNorm's affine included
            prm.copy_(torch.from_numpy(rng.normal(0.0, 0.7, tuple(prm.shape))))
    W = {k: v.detach().numpy() for k, v in layer.named_parameters()}
    query, memory = rng.normal(size=(3, 8)), rng.normal(size=(3, 5, 8))

    def lin(x, name):
        return x @ W[name + ".weight"].T + W[name + ".bias"]

    def layer_norm(x, name):
        mu, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
        return (x - mu) / np.sqrt(var + 1e-5) * W[name + ".weight"] + W[name + ".bias"]

    n, k, heads, dh = 3, 5, 2, 4
    weights, pooled = np.zeros((n, heads, dh, k)), np.zeros((n, heads * dh))
    for i in range(n):
        q, key, val = lin(query[i], "attn.q"), lin(memory[i], "attn.k"), lin(memory[i], "attn.v")  # (8,), (K, 8)
        for h in range(heads):
            ch = slice(h * dh, (h + 1) * dh)
            score = [sum(q[ch][c] * key[m, ch][c] for c in range(dh)) / math.sqrt(dh) for m in range(k)]
            for c in range(dh):  # softmax over the points of key channel c scaled by the point's score
                e = [math.exp(key[m, ch][c] * score[m]) for m in range(k)]
                weights[i, h, c] = [e_m / sum(e) for e_m in e]
            for cv in range(dh):  # value channel cv pooled with the weights of every key channel, then `down`
                z = [sum(weights[i, h, c, m] * val[m, ch][cv] for m in range(k)) for c in range(dh)]
                pooled[i, h * dh + cv] = sum(W["attn.down.weight"][0, c] * z[c] for c in range(dh)) \
                    + W["attn.down.bias"][0]
    attn_out = lin(pooled, "attn.out")
    x = layer_norm(query + attn_out, "norm1")
    want = layer_norm(x + lin(np.maximum(lin(x, "ff.0"), 0.0), "ff.3"), "norm2")

    with torch.no_grad():
        a, w = layer.attn(torch.from_numpy(query), torch.from_numpy(memory))
        got, w2 = layer(torch.from_numpy(query), torch.from_numpy(memory))
    np.testing.assert_allclose(w.numpy(), weights, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.numpy(), attn_out, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-6)
    assert torch.equal(w, w2) and np.abs(weights[:, :, 0] - weights[:, :, 1]).max() > 1e-3


def test_finite_losses_on_an_empty_frame_and_predictions():
    torch.manual_seed(0)
    model = models.build_model("ct3d", TINY_CT3D)
    empty = batch_of([np.zeros((0, 4), np.float32)], [np.zeros((0, 7))])
    loss, parts = model.loss(model(empty), empty)
    loss.backward()
    assert torch.isfinite(loss) and parts["num_fg_rois"] == 0
    car = [5.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.2]
    mixed = batch_of([np.zeros((0, 4), np.float32), box_points(car, on_faces=True)],
                     [np.zeros((0, 7)), np.array([car])])
    loss, parts = model.loss(model(mixed), mixed)
    assert torch.isfinite(loss) and parts["num_fg_rois"] > 0
    model.eval()
    with torch.no_grad():
        dets = model.predict(model(mixed), mixed)
        model.set_output_stage("proposals")
        first = model.predict(model(mixed), mixed)
    assert len(dets) == len(first) == 2 and all(torch.isfinite(d.boxes).all() for d in dets)
    with pytest.raises(ValueError, match="refined"):
        model.set_output_stage("rpn")


@pytest.mark.parametrize("how", ["scores_minus_inf", "zero_budget"])
def test_zero_proposals_through_the_full_model(how, monkeypatch):
    """The RPN proposes nothing: every score -inf (R padding slots, all masked), or a budget of 0 slots
    (R = 0, ct3d_head's r == 0 branch). Training and evaluation still run end to end."""
    cfg = copy.deepcopy(TINY_CT3D)
    rh = cfg["roi_head"]
    rh["targets"]["gt_jitter_copies"] = 0  # the RoIs are the proposals alone
    if how == "zero_budget":
        rh["proposals"]["train"]["post_nms_top_k"] = rh["proposals"]["test"]["post_nms_top_k"] = 0
        rh["targets"]["roi_per_image"] = 0
    torch.manual_seed(0)
    model = models.build_model("ct3d", cfg)
    if how == "scores_minus_inf":
        decode = model.head.decode

        def no_scores(rpn):
            boxes, scores = decode(rpn)
            return boxes, torch.full_like(scores, -math.inf)

        monkeypatch.setattr(model.head, "decode", no_scores)
    car = [5.0, 0.0, 0.8, 4.5, 1.9, 1.6, 0.2]
    batch = batch_of([box_points(car, on_faces=True), np.zeros((0, 4), np.float32)],
                     [np.array([car]), np.zeros((0, 7))])
    out = model(batch)
    assert not out.proposals.mask.any() and not out.refine.roi_mask.any()
    loss, parts = model.loss(out, batch)
    loss.backward()
    assert torch.isfinite(loss) and parts["num_fg_rois"] == 0 and parts["loss_rcnn_cls"] == 0
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(p.grad is not None and p.grad.any() for p in model.head.parameters())  # the RPN still learns
    model.eval()
    with torch.no_grad():
        out = model(batch)
        dets = model.predict(out, batch)
    assert not out.refine.roi_mask.any() and [len(d.boxes) for d in dets] == [0, 0]
    if how == "zero_budget":
        assert out.refine.rois.shape == (2, 0, 7) and out.refine.box_deltas.shape == (2, 0, 7)


def test_presets_build_and_paper_follows_the_published_configuration():
    cfg = load_run_config("ct3d", "paper")
    rh = cfg["model"]["roi_head"]
    assert (rh["num_points"], rh["hidden_dim"], rh["heads"], rh["enc_layers"], rh["dim_feedforward"]) == \
        (256, 256, 4, 3, 512)
    assert rh["targets"]["roi_per_image"] == 128 and rh["targets"]["cls_score_type"] == "roi_iou"
    assert rh["proposals"]["train"] == {"pre_nms_top_k": 9000, "post_nms_top_k": 512, "nms_threshold": 0.8}
    for preset in ("smoke", "cpu"):
        c = load_run_config("ct3d", preset)
        c["model"]["head"]["anchor_sizes"] = [[4.5, 1.9, 1.6]]
        assert models.build_model("ct3d", c["model"]).STAGES["roi_head"] == ["roi_head", "refine"]
    with pytest.raises(ValueError, match="unknown key.*num_pionts"):
        models.build_model("ct3d", {**TINY_CT3D, "roi_head": {**TINY_CT3D["roi_head"], "num_pionts": 3}})


@pytest.mark.slow
def test_overfit_a_few_frames_refines_the_boxes():
    """After a short overfit, the second stage moves jittered boxes closer to the cars."""
    from detbench.ops import boxes_iou3d_aligned
    from models.stages.two_stage import decode_refined

    torch.manual_seed(0)
    cars = [np.array([[4.6, 1.0, 0.8, 4.5, 1.9, 1.6, 0.1], [9.0, -1.5, 0.8, 4.2, 1.8, 1.5, 1.4]]),
            np.array([[6.0, -0.5, 0.9, 4.8, 2.0, 1.8, -0.2]])]
    pts = [np.concatenate([box_points(b, rng=i, on_faces=True) for i, b in enumerate(bs)]) for bs in cars]
    batch = batch_of(pts, cars)
    cfg = {**TINY_CT3D, "roi_head": {**TINY_CT3D["roi_head"], "hidden_dim": 32, "mlp_hidden": 32, "fc": [64]}}
    model = models.build_model("ct3d", cfg)
    opt = torch.optim.AdamW(model.parameters(), lr=0.003)
    history = []
    for _ in range(200):
        loss, parts = model.loss(model(batch), batch)
        history.append(parts)
        opt.zero_grad()
        loss.backward()
        opt.step()
    early = np.mean([h["loss_rcnn_corner"] for h in history[:10]])
    late = np.mean([h["loss_rcnn_corner"] for h in history[-10:]])
    assert late < 0.6 * early
    # fixed jittered copies of the cars as RoIs: refinement raises their mean 3D IoU
    g = torch.Generator().manual_seed(3)
    gt = torch.as_tensor(np.concatenate(cars), dtype=torch.float32)
    rois = gt.repeat(4, 1)
    rois[:, :2] += torch.randn(len(rois), 2, generator=g) * 0.3
    rois[:, 6] += torch.randn(len(rois), generator=g) * 0.1
    frame = torch.tensor([0, 0, 1] * 4)
    model.eval()
    with torch.no_grad():
        before, after = [], []
        for i in (0, 1):
            r = rois[frame == i][None]
            feats = model.roi_head(batch.points, r)
            _, reg = model.refine(feats)
            boxes = decode_refined(reg, r, model.coder)[0]
            target = gt.repeat(4, 1)[frame == i]
            before.append(boxes_iou3d_aligned(r[0], target))
            after.append(boxes_iou3d_aligned(boxes, target))
    before, after = torch.cat(before).mean(), torch.cat(after).mean()
    assert float(after) > float(before) + 0.05, \
        f"mean 3D IoU of jittered RoIs {float(before):.3f} -> refined {float(after):.3f}"

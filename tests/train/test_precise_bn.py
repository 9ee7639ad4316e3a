"""BatchNorm statistics recomputed for a checkpoint's weights (detbench.train.precise_bn)."""
import torch
from torch import nn

from detbench.train.precise_bn import recompute_bn_statistics


def _model():
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4), nn.ReLU(), nn.Dropout(0.5), nn.Linear(4, 2))


def test_the_running_statistics_are_the_equal_weight_average_over_the_batches():
    model = _model()
    model[1].running_mean.fill_(123.0)  # stale statistics, as after a phase of high learning rate
    batches = [torch.randn(8, 3) * (k + 1) + k for k in range(5)]
    weights = {k: v.clone() for k, v in model.state_dict().items() if "running" not in k and "num_batches" not in k}
    model.eval()
    torch.manual_seed(7)
    expected_next = torch.rand(3)
    torch.manual_seed(7)
    assert recompute_bn_statistics(model, batches, lambda m, b: m(b)) == 5
    assert torch.equal(torch.rand(3), expected_next)  # the random stream is the one before (dropout drew from it)
    assert not model.training and model[1].momentum == 0.1  # mode and momentum restored
    with torch.no_grad():
        feats = [model[0](b) for b in batches]
    want_mean = torch.stack([f.mean(0) for f in feats]).mean(0)
    want_var = torch.stack([f.var(0, unbiased=True) for f in feats]).mean(0)
    torch.testing.assert_close(model[1].running_mean, want_mean)
    torch.testing.assert_close(model[1].running_var, want_var)
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in weights.items())  # no weight moved


def test_no_batch_or_no_batchnorm_leaves_everything_as_it_was():
    model = _model()
    model[1].running_mean.fill_(2.0)
    assert recompute_bn_statistics(model, [], lambda m, b: m(b)) == 0
    assert torch.equal(model[1].running_mean, torch.full((4,), 2.0)) and model[1].num_batches_tracked == 0
    plain = nn.Linear(3, 2)
    calls = []
    assert recompute_bn_statistics(plain, [torch.randn(2, 3)], lambda m, b: calls.append(b)) == 0 and not calls

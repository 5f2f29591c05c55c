"""The class-balanced done loss weighs done and not-done frames half each."""
import torch
import torch.nn.functional as F

from stages.train_wm.train import done_loss


def test_balanced_bce_is_the_mean_of_the_two_class_means():
    logit = torch.tensor([[2.0, -1.0, 0.5, 3.0], [0.0, -2.0, 1.0, 0.0]])  # (B, T)
    target = torch.tensor([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]])
    valid = torch.tensor([[1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 0.0]])
    per = F.binary_cross_entropy_with_logits(logit, target, reduction="none")
    pos = per[0, 3]
    neg = torch.cat([per[0, :3], per[1, :3]]).mean()
    assert torch.allclose(done_loss(logit, target, valid, "bce", balance=True), (pos + neg) / 2)
    plain = (per * valid).sum() / valid.sum()
    assert torch.allclose(done_loss(logit, target, valid, "bce"), plain)
    assert not torch.allclose(plain, (pos + neg) / 2)


def test_balanced_loss_without_positives_is_the_plain_mean():
    logit, target, valid = torch.randn(3, 5), torch.zeros(3, 5), torch.ones(3, 5)
    for kind in ("bce", "rmse"):
        assert torch.allclose(done_loss(logit, target, valid, kind, balance=True), done_loss(logit, target, valid, kind))

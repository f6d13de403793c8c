"""kpd6d.ema.WeightEMA: the averaging formula, what validation / checkpoints / export see, and resuming."""

from __future__ import annotations

import pytest
import pytorch_lightning as pl
import torch

from kpd6d.ema import WeightEMA, ema_callback


class _Tiny(pl.LightningModule):
    """Linear regression with a BatchNorm (a floating buffer) and plain SGD: deterministic."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.lin = torch.nn.Linear(3, 1)
        self.bn = torch.nn.BatchNorm1d(3)
        self.seen_in_validation: list[torch.Tensor] = []

    def forward(self, x):
        return self.lin(self.bn(x))

    def training_step(self, batch, batch_idx):
        x, y = batch
        return torch.nn.functional.mse_loss(self(x), y)

    def validation_step(self, batch, batch_idx):
        self.seen_in_validation.append(self.lin.weight.detach().clone())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _loader(n: int = 32):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(n, 3, generator=g)
    y = x @ torch.tensor([[1.0], [-2.0], [0.5]]) + 0.3
    return torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, y), batch_size=8)


def _trainer(tmp_path, callbacks, max_epochs, **kw):
    return pl.Trainer(default_root_dir=str(tmp_path), max_epochs=max_epochs, callbacks=callbacks, logger=False,
                      enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                      accelerator="cpu", devices=1, **kw)


def test_update_follows_the_ramped_formula():
    net = torch.nn.Linear(2, 2)
    ema = WeightEMA(decay=0.9)
    ema.update(net)  # first call copies
    expected = {k: v.clone() for k, v in net.state_dict().items()}
    for n in range(1, 30):
        with torch.no_grad():
            for p in net.parameters():
                p.add_(torch.randn_like(p))
        ema.update(net)
        d = min(0.9, (1 + n) / (10 + n))
        for k, v in net.state_dict().items():
            expected[k] = d * expected[k] + (1 - d) * v
    for k in expected:
        torch.testing.assert_close(ema.ema[k], expected[k])
    assert ema.num_updates == 29 and ema.current_decay() == pytest.approx(30 / 39)  # still ramping (< 0.9)


def test_bad_decay_is_refused():
    with pytest.raises(ValueError, match="decay"):
        WeightEMA(decay=1.0)
    assert ema_callback(None) == [] and ema_callback(0) == []
    assert isinstance(ema_callback(0.99)[0], WeightEMA)


def test_validation_and_checkpoints_see_the_average_training_the_raw_weights(tmp_path):
    from pytorch_lightning.callbacks import ModelCheckpoint

    ema = WeightEMA(decay=0.5)
    module = _Tiny()
    ck = ModelCheckpoint(dirpath=tmp_path / "ck", filename="last", monitor=None)
    _trainer(tmp_path, [ema, ck], max_epochs=3).fit(module, _loader(), _loader(8))
    assert ema.num_updates == 12  # 3 epochs x 4 steps; the call at fit start only copies
    # validation ran with the average of that moment (differs from the raw weights then)
    assert len(module.seen_in_validation) == 3
    ckpt = torch.load(tmp_path / "ck" / "last.ckpt", weights_only=False)
    torch.testing.assert_close(ckpt["state_dict"]["lin.weight"], module.seen_in_validation[-1])
    torch.testing.assert_close(ckpt["state_dict"]["lin.weight"], ema.ema["lin.weight"])
    torch.testing.assert_close(ckpt["state_dict"]["bn.running_mean"], ema.ema["bn.running_mean"])
    # after fit the module holds the raw weights again; apply_to writes the average
    raw = module.lin.weight.detach().clone()
    assert not torch.allclose(raw, ema.ema["lin.weight"])
    torch.testing.assert_close(ckpt["callbacks"]["WeightEMA"]["raw"]["lin.weight"], raw)
    ema.apply_to(module)
    torch.testing.assert_close(module.lin.weight, ema.ema["lin.weight"])


def test_resume_continues_raw_weights_and_average(tmp_path):
    from pytorch_lightning.callbacks import ModelCheckpoint

    def run(root, epochs, ckpt_path=None):
        ema = WeightEMA(decay=0.7)
        module = _Tiny()
        ck = ModelCheckpoint(dirpath=root / "ck", filename="last", monitor=None)
        _trainer(root, [ema, ck], max_epochs=epochs).fit(module, _loader(), _loader(8), ckpt_path=ckpt_path)
        return module, ema

    straight, ema_straight = run(tmp_path / "a", 4)
    run(tmp_path / "b", 2)
    resumed, ema_resumed = run(tmp_path / "b", 4, ckpt_path=str(tmp_path / "b" / "ck" / "last.ckpt"))
    assert ema_resumed.num_updates == ema_straight.num_updates
    torch.testing.assert_close(resumed.lin.weight, straight.lin.weight)
    for k in ema_straight.ema:
        torch.testing.assert_close(ema_resumed.ema[k], ema_straight.ema[k])

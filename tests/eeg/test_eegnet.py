"""EEGNet: output shapes with valid padding, parameter count, constraints, scripting."""

from __future__ import annotations

import pytest
import torch

from services.eeg.decoding.eegnet import DENSE_MAX_NORM, SPATIAL_MAX_NORM, EEGNet, count_parameters


def test_output_shape_and_feature_size() -> None:
    model = EEGNet(64, 2, 103)
    assert model.n_features == 4 * 3  # 103 -> 72 -> 18 -> 12 -> 3 samples, F2 = 4
    out = model(torch.randn(5, 64, 103))
    assert out.shape == (5, 2)
    assert EEGNet(8, 3, 200)(torch.randn(2, 8, 200)).shape == (2, 3)


def test_parameter_count_for_64_channels() -> None:
    # temporal 4*32 + bn 8 + spatial 8*64 + bn 16 + sep-depth 8*7 + point 8*4 + bn 8
    # + dense 12*2+2
    assert count_parameters(EEGNet(64, 2, 103)) == 128 + 8 + 512 + 16 + 56 + 32 + 8 + 26 == 786


def test_valid_padding_refuses_too_short_epochs() -> None:
    with pytest.raises(ValueError, match="too short"):
        EEGNet(64, 2, 40)


def test_max_norm_constraints() -> None:
    model = EEGNet(16, 2, 103)
    with torch.no_grad():
        model.conv_spatial.weight.mul_(100)
        model.final_layer.weight.mul_(100)
    model.apply_max_norm()
    spatial = model.conv_spatial.weight.flatten(1).norm(dim=1)
    dense = model.final_layer.weight.norm(dim=1)
    assert torch.all(spatial <= SPATIAL_MAX_NORM + 1e-5)
    assert torch.all(dense <= DENSE_MAX_NORM + 1e-5)


def test_scriptable_and_rebuildable_from_hparams() -> None:
    model = EEGNet(64, 2, 103).eval()
    x = torch.randn(3, 64, 103)
    scripted = torch.jit.script(model)
    torch.testing.assert_close(scripted(x), model(x))
    clone = EEGNet(**model.hparams).eval()
    clone.load_state_dict(model.state_dict())
    torch.testing.assert_close(clone(x), model(x))


def test_reset_parameters_from_a_generator_equals_global_seeding() -> None:
    """Seeded init without the global generator gives torch's own initial weights."""
    torch.manual_seed(7)
    reference = EEGNet(64, 2, 103)
    state = torch.random.get_rng_state()
    model = EEGNet(64, 2, 103)
    model.reset_parameters(torch.Generator().manual_seed(7))
    for (name, a), b in zip(
        reference.state_dict().items(), model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)
    assert not torch.equal(torch.random.get_rng_state(), state)  # the constructor drew
    model.reset_parameters(torch.Generator().manual_seed(7))
    torch.testing.assert_close(model.final_layer.bias, reference.final_layer.bias)


def test_generator_dropout_matches_torch_dropout_and_leaves_global_rng() -> None:
    x = torch.randn(4, 8, 1, 18)
    torch.manual_seed(3)
    expected = torch.nn.functional.dropout(x, p=0.25, training=True)
    model = EEGNet(16, 2, 103).train()
    model.set_dropout_generator(torch.Generator().manual_seed(3))
    state = torch.random.get_rng_state()
    torch.testing.assert_close(model.drop_1(x), expected, rtol=0, atol=0)
    assert torch.equal(torch.random.get_rng_state(), state)
    model.eval()
    assert torch.equal(model.drop_1(x), x)

import pytest
import torch

from tactile_slam.geometry.morphology import as_weights, dilate, erode, fill_holes


@pytest.mark.parametrize("size", [3, 5, 7, 15])
@pytest.mark.parametrize("border_is_contact", [True, False])
def test_backends_agree(size, border_is_contact):
    m = torch.rand(3, 40, 50, generator=torch.Generator().manual_seed(size)) > 0.4
    torch.testing.assert_close(erode(m, size, border_is_contact, backend="cv2"),
                               erode(m, size, border_is_contact, backend="torch"))
    torch.testing.assert_close(dilate(m, size, backend="cv2"), dilate(m, size, backend="torch"))


def test_full_mask_border_semantics():
    """OpenCV-style erosion keeps a full mask; non-contact border removes a band."""
    m = torch.ones(1, 20, 30, dtype=torch.bool)
    assert erode(m, 5, border_is_contact=True).all()
    e = erode(m, 5, border_is_contact=False)
    assert not e[0, :2].any() and not e[0, -2:].any() and not e[0, :, :2].any() and not e[0, :, -2:].any()
    assert e[0, 2:-2, 2:-2].all()


def test_single_pixel_dilation_is_square():
    m = torch.zeros(1, 11, 11, dtype=torch.bool)
    m[0, 5, 5] = True
    d = dilate(m, 5)
    assert d.sum() == 25 and d[0, 3:8, 3:8].all()


def test_bad_backend():
    with pytest.raises(ValueError, match="backend"):
        dilate(torch.zeros(1, 4, 4, dtype=torch.bool), 3, backend="gpu")


def test_fill_holes_backends_agree_and_keep_open_regions():
    m = torch.zeros(2, 30, 40, dtype=torch.bool)
    m[:, 5:20, 5:20] = True
    m[:, 9:14, 9:14] = False  # enclosed hole -> filled
    m[1, 0:10, 30:40] = True
    m[1, 0:5, 33:37] = False  # touches the border -> stays open
    cpu = fill_holes(m)
    assert cpu[:, 9:14, 9:14].all()
    assert not cpu[1, 0:5, 33:37].any()
    torch.testing.assert_close(cpu, fill_holes(m, backend="torch"))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_as_weights_is_the_float_mask(device, dtype):
    mask = torch.rand((2, 5, 7), generator=torch.Generator().manual_seed(0)) > 0.5
    w = as_weights(mask.to(device), dtype)
    assert w.dtype == dtype and w.shape == mask.shape and w.device.type == torch.device(device).type
    assert torch.equal(w.cpu(), mask.to(dtype))


def test_as_weights_of_a_numeric_mask_keeps_its_shape():
    mask = torch.tensor([[0.0, 1.0, 1.0]])
    assert torch.equal(as_weights(mask, torch.float64), mask.double())

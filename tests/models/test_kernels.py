import torch

from models.kernels import filter_padded, pad_for_kernel, unnormalised_weights


# eqs. 3–4 composed from the primitives the denoiser uses (it pads once and reuses the padding).
def kernel_weights(logits: list[torch.Tensor]) -> list[torch.Tensor]:
    """Joint softmax over all frames' k² logits at each pixel (eq. 4), one tensor per frame."""
    joint = torch.softmax(torch.cat(list(logits), dim=1), dim=1)
    return list(torch.split(joint, [l.shape[1] for l in logits], dim=1))


def apply_kernels(images, logits, k: int) -> torch.Tensor:
    """Filter image(s) (N,C,H,W) with per-pixel kernels from logits (N,k²,H,W) (eq. 3); with
    lists, one kernel per frame and one softmax over all of them (eq. 4).
    Tap index dy·k + dx weights pixel (y + dy − k//2, x + dx − k//2)."""
    if isinstance(images, torch.Tensor):
        images, logits = [images], [logits]
    if len(images) != len(logits):
        raise ValueError(f"{len(images)} images but {len(logits)} logit maps")
    for l in logits:
        if l.shape[1] != k * k:
            raise ValueError(f"logits have {l.shape[1]} channels, expected k²={k * k}")
    weights = unnormalised_weights(torch.cat(list(logits), dim=1))   # cat: a fresh tensor, safe in place
    return filter_padded([pad_for_kernel(i, k) for i in images], weights, k)


def test_kernel_weights_are_non_negative_and_sum_to_one_jointly_across_frames():
    logits = [torch.randn(2, 9, 5, 6) * 10 for _ in range(3)]
    weights = kernel_weights(logits)
    assert all((w >= 0).all() for w in weights)
    total = sum(w.sum(dim=1) for w in weights)
    torch.testing.assert_close(total, torch.ones(2, 5, 6))
    # per frame the weights do NOT sum to one: the softmax is joint
    assert not torch.allclose(weights[0].sum(1), torch.ones(2, 5, 6))


def test_single_scale_output_lies_in_convex_hull_of_input_neighbourhood():
    k = 5
    image = torch.rand(1, 3, 9, 11) * 100
    out = apply_kernels(image, torch.randn(1, k * k, 9, 11) * 5, k)
    padded = torch.nn.functional.pad(image, (2, 2, 2, 2), mode="replicate")
    windows = padded.unfold(2, k, 1).unfold(3, k, 1)          # (1,3,9,11,k,k) – fine at this size
    lo, hi = windows.amin(dim=(-1, -2)), windows.amax(dim=(-1, -2))
    assert (out >= lo - 1e-4).all() and (out <= hi + 1e-4).all()


def test_temporal_output_lies_within_union_of_frame_neighbourhoods():
    k = 3
    images = [torch.rand(1, 3, 6, 7) for _ in range(3)]
    images[1] += 5
    out = apply_kernels(images, [torch.randn(1, 9, 6, 7) for _ in images], k)
    assert out.min() >= 0 and out.max() <= 6 + 1e-5


def test_delta_kernel_is_identity_and_offset_kernel_shifts():
    k = 3
    image = torch.rand(1, 3, 5, 5)
    logits = torch.full((1, 9, 5, 5), -1e4)
    logits[:, 4] = 0                                  # centre tap
    torch.testing.assert_close(apply_kernels(image, logits.clone(), k), image)
    logits = torch.full((1, 9, 5, 5), -1e4)
    logits[:, 5] = 0                                  # tap (dy=1, dx=2): pixel to the right
    out = apply_kernels(image, logits, k)
    torch.testing.assert_close(out[..., :-1], image[..., 1:])


def test_apply_kernels_backward_reaches_logits_and_images():
    image = torch.rand(1, 3, 4, 4, requires_grad=True)
    logits = torch.randn(1, 9, 4, 4, requires_grad=True)
    apply_kernels(image, logits, 3).square().sum().backward()
    assert image.grad.isfinite().all() and logits.grad.isfinite().all()
    assert logits.grad.abs().sum() > 0


def test_apply_kernels_gradient_matches_explicit_softmax_filtering():
    image = torch.rand(1, 2, 4, 5, dtype=torch.float64)
    logits = [torch.randn(1, 9, 4, 5, dtype=torch.float64, requires_grad=True) for _ in range(2)]
    frames = [image, image.flip(-1)]
    apply_kernels(frames, logits, 3).sum().backward()
    fast = [l.grad.clone() for l in logits]
    for l in logits:
        l.grad = None
    padded = [torch.nn.functional.pad(f, (1, 1, 1, 1), mode="replicate") for f in frames]
    ref = sum(w[:, t:t + 1] * p[:, :, t // 3:t // 3 + 4, t % 3:t % 3 + 5]
              for w, p in zip(kernel_weights(logits), padded) for t in range(9))
    ref.sum().backward()
    for a, l in zip(fast, logits):
        torch.testing.assert_close(a, l.grad)

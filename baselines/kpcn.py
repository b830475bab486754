"""Kernel-predicting convolutional network (Bako et al., "Kernel-Predicting Convolutional Networks for
Denoising Monte Carlo Renderings", SIGGRAPH 2017), adapted to SRD.

Original: `layers` (9) 5x5 conv layers of 100 channels read the noisy radiance and auxiliary features;
the last layer predicts per pixel a k x k kernel (k = 21), softmax-normalized, which filters the noisy
radiance around that pixel. The diffuse/specular split is not used (neither does the paper, Sec. 5).
SRD adaptation: at every LR pixel the network predicts s*s kernels, one per HR sub-pixel of its s x s
output block, each a softmax-normalized weighting of the k x k LR neighbourhood of the noisy radiance
(replicate-padded at the border, so weights summing to one keep a constant image constant); the s*s
filtered values are then arranged by pixel shuffle. The paper's "attach a pixel-shuffle layer" thus acts
on filtered radiance, keeping the kernel-prediction principle. Input is radiance concatenated with the
gBuffer; width (`channels`) is chosen to the compute budget. With k = 21 the last layer (5x5, C to
s*s*441 channels) dominates the MACs, so the budget leaves KPCN narrow.
"""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from baselines import fold_time, unfold_time, with_gbuffer


class KernelFilter(nn.Module):
    """Apply per-pixel kernels: out[n, s, c] = sum_tap w[n, s, tap] * x_pad[n, c, neighbourhood(tap)].

    Pixel-major: the k x k neighbourhoods of a band of rows are gathered from the padded input by
    strided views (one copy, (pixels, C, k*k)), and each pixel's kernels are contracted with them in
    one batched matmul (pixels, S, k*k) @ (pixels, k*k, C). Bands bound the gathered
    neighbourhoods to `max_elements` values (a 1080p frame would need 2.7 GB at once). A loop over taps
    with slicing is far slower to train: each slice's backward allocates a full-size gradient (33 s per
    training step at the cpu scale, against well under a second here). The contraction is a batched
    matmul, so FlopCounterMode counts it; `macs` declares the same for the analytic count.
    """

    def __init__(self, filter_size, max_elements=1 << 25):
        super().__init__()
        self.filter_size, self.max_elements = filter_size, max_elements

    def forward(self, x, weights):
        """x: (N, C, h, w); weights: (N, S, k*k, h, w), normalized over k*k -> (N, S, C, h, w)."""
        n, c, h, w = x.shape
        k, pad = self.filter_size, self.pad(x)
        rows = max(1, self.max_elements // max(1, n * c * k * k * w))
        bands = [self.filter_rows(pad, weights[..., top:top + rows, :].permute(0, 3, 4, 1, 2), top)
                 for top in range(0, h, rows)]
        return torch.cat(bands, dim=1).permute(0, 3, 4, 1, 2)

    def pad(self, x):
        """(N, C, h+k-1, w+k-1), contiguous: x replicate-padded by k // 2; the input of filter_rows."""
        return F.pad(x, (self.filter_size // 2,) * 4, mode="replicate").contiguous()

    def filter_rows(self, pad, weights, row0):
        """Rows row0..row0+rows-1 of the filtered image, (N, rows, w, S, C), from the whole padded input
        `pad` (from self.pad) and those rows' kernels `weights` (N, rows, w, S, k*k)."""
        k, (n, rows, w, s, taps) = self.filter_size, weights.shape
        c = pad.shape[1]
        # (N, C, rows, w, k, k) views of the neighbourhoods -> one copy (pixels, C, k*k), copying runs of
        # k contiguous values
        hood = pad[:, :, row0:row0 + rows + k - 1].unfold(2, k, 1).unfold(3, k, 1)
        cols = hood.permute(0, 2, 3, 1, 4, 5).reshape(n * rows * w, c, taps)
        out = torch.bmm(weights.reshape(n * rows * w, s, taps), cols.to(weights.dtype).transpose(1, 2))
        return out.view(n, rows, w, s, c)

    def macs(self, inputs, output):
        """One MAC per output value per tap."""
        return output.numel() * self.filter_size ** 2


def bilinear_stencil(scale: int, filter_size: int) -> torch.Tensor:
    """(s*s, k*k) weights over the k x k LR neighbourhood that reproduce F.interpolate(bilinear,
    align_corners=False) for each HR sub-pixel (row-major sub-pixel order, as pixel_shuffle reads it)."""
    centre = filter_size // 2
    taps_1d = [[0.0] * filter_size for _ in range(scale)]  # plain floats: models are also built on "meta"
    for sub in range(scale):
        pos = (sub + 0.5) / scale - 0.5          # LR offset of the sub-pixel from its pixel's centre
        left = math.floor(pos)
        taps_1d[sub][centre + left] += 1 - (pos - left)
        taps_1d[sub][centre + left + 1] += pos - left
    taps_1d = torch.tensor(taps_1d, device="cpu")
    return torch.einsum("ay,bx->abyx", taps_1d, taps_1d).reshape(scale * scale, filter_size * filter_size)


def start_as_bilinear(last_conv: nn.Conv2d, scale: int, filter_size: int, share: float) -> None:
    """Make every predicted kernel start as `share` x the bilinear stencil + (1 - share) x a k x k box:
    zero weights, log-probabilities as bias. share = 1 would start exactly at "Input bilinear", but its
    other taps would get (softmax) gradients near zero and never widen into a denoising kernel."""
    probs = share * bilinear_stencil(scale, filter_size) + (1 - share) / filter_size ** 2
    nn.init.zeros_(last_conv.weight)
    with torch.no_grad():
        last_conv.bias.copy_(probs.log().reshape(-1).to(last_conv.bias.device))


class KPCN(nn.Module):
    recurrent = False

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, channels=100, layers=9, kernel_size=5,
                 filter_size=21, bilinear_start: float = 0.0):
        super().__init__()
        if filter_size % 2 == 0:
            raise ValueError("filter_size must be odd (kernels are centred on the pixel)")
        self.gbuffer_channels, self.scale, self.filter_size = gbuffer_channels, scale, filter_size
        pad = kernel_size // 2
        convs = [nn.Conv2d(in_channels + gbuffer_channels, channels, kernel_size, padding=pad), nn.ReLU()]
        for _ in range(layers - 2):
            convs += [nn.Conv2d(channels, channels, kernel_size, padding=pad), nn.ReLU()]
        convs.append(nn.Conv2d(channels, scale * scale * filter_size ** 2, kernel_size, padding=pad))
        self.net = nn.Sequential(*convs)
        self.filter = KernelFilter(filter_size)
        self.band_elements = 1 << 22  # kernel weights per band of rows in forward (16 MB in float32)
        if bilinear_start:
            start_as_bilinear(convs[-1], scale, filter_size, bilinear_start)

    def kernels(self, x, g):
        """Per-pixel kernels (N, s*s, k*k, h, w), each summing to one over its k*k taps."""
        logits = self.net(fold_time(with_gbuffer(x, g, self.gbuffer_channels)))
        n, _, h, w = logits.shape
        return logits.view(n, self.scale ** 2, self.filter_size ** 2, h, w).softmax(dim=2)

    def _kernel_bands(self, features):
        """(first row, kernels (N, rows, w, s*s, k*k) of rows first..) per band of rows: the last conv
        and the softmax on `band_elements` kernel weights at a time, pixel-major. Equal to kernels(),
        but a 1080p frame's 1764 x h x w logits (3.7 GB in float32) never exist at once, and each band
        is filtered while in cache."""
        last = self.net[-1]
        pad = last.padding[0]
        n, _, h, w = features.shape
        rows = max(1, self.band_elements // (n * last.out_channels * w))
        # zero rows, as the conv's own padding; channels-last, so the logits come out pixel-major
        padded = F.pad(features, (0, 0, pad, pad)).contiguous(memory_format=torch.channels_last)
        for top in range(0, h, rows):
            bottom = min(h, top + rows)
            logits = F.conv2d(padded[:, :, top:bottom + 2 * pad], last.weight, last.bias, padding=(0, pad))
            logits = logits.permute(0, 2, 3, 1).reshape(n, bottom - top, w, self.scale ** 2, self.filter_size ** 2)
            yield top, logits.softmax(dim=-1)

    def macs(self, inputs, output):
        """The last conv and the kernel filtering, which forward runs band by band as a functional conv
        and KernelFilter.filter_rows (bench.macs protocol; FlopCounterMode sees both)."""
        x = inputs[0]
        pixels = x.shape[0] * x.shape[1] * x.shape[-2] * x.shape[-1]
        last = self.net[-1]
        conv = pixels * last.out_channels * last.in_channels * last.kernel_size[0] * last.kernel_size[1]
        return conv + pixels * self.scale ** 2 * 3 * self.filter_size ** 2

    def forward(self, x, g):
        b = x.shape[0]
        features = self.net[:-1](fold_time(with_gbuffer(x, g, self.gbuffer_channels)))
        radiance = self.filter.pad(fold_time(x)[:, :3])
        filtered = torch.cat([self.filter.filter_rows(radiance, weights, top)
                              for top, weights in self._kernel_bands(features)], dim=1)  # (N, h, w, s*s, 3)
        n, h, w, _, c = filtered.shape
        s = self.scale
        # sub-pixel (i, j) of LR pixel (y, x) is HR pixel (s*y + i, s*x + j), as pixel_shuffle places it
        out = filtered.view(n, h, w, s, s, c).permute(0, 5, 1, 3, 2, 4).reshape(n, c, s * h, s * w)
        return {"final": unfold_time(out.to(x.dtype), b)}

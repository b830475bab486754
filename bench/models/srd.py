"""The paper's end-to-end super-resolution + denoising network (Sec. 3, 4.2; Fig. 3 and 7).

Default (the paper's final model, stage_order="sr_dn"):

  LR noisy x, LR gBuffer g
   -> SR stage (EDSR-lite at LR): head conv, `sr_blocks` ResBlocks with CFM, body conv + global residual
      ("deep features"), PixelShuffleUp x`scale` to `channels` HR features (channel aug); a 3x3 conv
      "RGB head" on them gives the HR-noisy estimate (the "intermediate" output).
   -> Denoise stage (deformable recurrent auto-encoder at HR, after Chaitanya et al. 2017):
        encoder level j = 1..dn_levels at 1/2^(j-1) of HR: conv_in, then a recurrent block
        conv(concat(features, hidden_j)) -> conv whose output is the new hidden_j and the skip; 2x2 max-pool.
        bottleneck at 1/2^dn_levels: the same recurrent structure.
        decoder block "u_j" (j = dn_levels..1): nearest x2 upsample, concat the encoder skip of level j,
        conv -> CFM -> ReLU -> conv -> CFM -> ReLU (a "CFM block"). u1 is the full-resolution block
        nearest the output, u2 the next one down, ... (paper Table 7). The second conv of u1..u_n is
        deformable for n = dn_deform_blocks; CFM is used only in the decoder.
        output conv -> 3-channel HR result ("final").
  Skip (IPT): the SR deep features (LR, before upsampling) are added to the output of conv_in at the
  encoder level whose size is LR (level 2 when scale=2, level 1 when scale=1). SR and denoiser both use
  `channels` channels, so no 1x1 projection is needed.
  gBuffer (it exists only at LR): each stage has its own ConditionNet run on the LR gBuffer. The SR
  stage uses it at LR. The denoiser's conditioning is brought to its level-1 size by NEAREST upsampling
  and to decoder level j by 2^(j-1) average pooling (which reproduces the LR features exactly at the
  LR-sized level).
  gbuffer_mode="concat" ("Simple End2End"): no CFM/ConditionNet; g is concatenated to the first stage's
  input and, nearest-upsampled to the second stage's size, to the second stage's input.
  stage_order="dn_sr": the recurrent denoiser runs at LR first (its output has `channels` channels with
  channel_aug, else 3), then the SR stage upsamples to the final HR image; with skip=True the
  denoiser's last decoder features (u1, LR) are added to the SR stage's head features. There is no
  intermediate output in this order (its first stage's target would be LR clean, not HR noisy).
  Padding: inputs are replicate-padded at bottom/right so the denoiser's input is a multiple of
  2^dn_levels (it pools dn_levels times: the network input is padded to 2^dn_levels / scale in sr_dn,
  2^dn_levels in dn_sr), and the output is cropped back; any input size works. Replicate, not
  reflect, because reflect cannot pad more than the input size (e.g. 13x7 -> 16x16).
  Recurrence: each encoder level and the bottleneck keep their output as hidden state, concatenated
  with the next frame's features at that level (RAE); it is zero at the start of every forward call.

Cost of the default model at 960x540 input: 0.518 M parameters, 264.7 GMac in convs and the
deformable convs' weight products, plus 3.2 GMac of bilinear sampling: 267.8 GMac, as bench.macs counts
it (paper Table 5: 258.29 GMac). The paper does not give the size of its gBuffer
encoder or of the CFM layers: with `cond_channels=16` conditioning channels (16 for the ConditionNet output and the CFM 1x1 convs) the
model lands within +3% of the paper's 260 GMac budget (32 would be 282.6, +8.7%; 8 would be 260.5).
The input is padded from 540 to 544 rows (+0.7%).

Cascade training (paper Table 3 "Cascade" rows) uses forward_stage(stage, x, g): each stage alone, see
its docstring. scale=1 (denoise-only task) keeps the same structure with a scale-1 "SR" front stage.
"""
import copy

import torch
import torch.nn as nn
import torch.nn.functional as F

from bench.hdr import transforms
from bench.nn import (CFM, ConditionNet, DeformConv2d, EDSRTrunk, PixelShuffleUp, RecurrentBlock, conv3x3,
                     run_sequence, upsampled_input, zero_init)


class SRStage(nn.Module):
    """EDSR-lite: the EDSR trunk (ResBlocks with optional CFM/dilation/deformable conv2), PixelShuffleUp
    to `out_ch` channels, optional 3x3 RGB head on the upsampled features."""

    def __init__(self, in_ch, out_ch, channels, blocks, scale, cond_channels, deform_blocks, dilation,
                 rgb_head):
        super().__init__()
        self.trunk = EDSRTrunk(in_ch, channels, blocks, dilation=dilation, deform_blocks=deform_blocks,
                               cond_channels=cond_channels)
        self.up = PixelShuffleUp(channels, out_ch, scale)
        self.rgb = conv3x3(out_ch, 3) if rgb_head else None

    def forward(self, x, cond=None, skip=None):
        """Returns (upsampled features, RGB head output or None, deep LR features before upsampling)."""
        deep = self.trunk(x, cond, skip)
        out = self.up(deep)
        return out, (self.rgb(out) if self.rgb is not None else None), deep


class DecoderBlock(nn.Module):
    """CFM block: concat(upsampled, skip) -> conv -> [CFM] -> ReLU -> conv (deformable?) -> [CFM] -> ReLU."""

    def __init__(self, channels, cond_channels, deformable):
        super().__init__()
        self.conv1 = conv3x3(2 * channels, channels)
        self.conv2 = DeformConv2d(channels, channels) if deformable else conv3x3(channels, channels)
        self.cfm1 = CFM(channels, cond_channels) if cond_channels > 0 else None
        self.cfm2 = CFM(channels, cond_channels) if cond_channels > 0 else None

    def forward(self, x, skip, cond=None):
        y = self.conv1(torch.cat((x, skip), dim=1))
        y = self.cfm1(y, cond, relu=True) if self.cfm1 is not None else F.relu(y)
        y = self.conv2(y)
        return self.cfm2(y, cond, relu=True) if self.cfm2 is not None else F.relu(y)


class RecurrentDenoiser(nn.Module):
    """Recurrent U-Net auto-encoder: `levels` encoder levels + recurrent bottleneck + decoder u_levels..u1.

    decoder[i] is block u_{levels-i}; the last `deform_blocks` (u1, u2, ...) have a deformable conv2.
    Input size must be a multiple of 2^levels.
    """

    def __init__(self, in_ch, out_ch, channels, levels, cond_channels, deform_blocks, skip_level):
        super().__init__()
        if not 0 <= deform_blocks <= levels:
            raise ValueError(f"dn_deform_blocks must be in 0..{levels}, got {deform_blocks}")
        self.levels, self.channels, self.skip_level = levels, channels, skip_level
        self.encoder = nn.ModuleList(RecurrentBlock(in_ch if j == 0 else channels, channels)
                                     for j in range(levels + 1))  # last one = bottleneck
        self.decoder = nn.ModuleList(DecoderBlock(channels, cond_channels, deformable=j <= deform_blocks)
                                     for j in range(levels, 0, -1))
        self.out = conv3x3(channels, out_ch)

    def init_hidden(self, batch, height, width, like):
        """Zero hidden states, one per encoder level and the bottleneck (level j at 1/2^j size)."""
        return [like.new_zeros(batch, self.channels, height >> j, width >> j) for j in range(self.levels + 1)]

    def forward(self, x, hidden, conds=None, skip=None):
        """x: (B, C_in, H, W); hidden: list from init_hidden (None: zeros, a fresh sequence); conds:
        per-level conditioning (index j-1 for u_j) or None; skip: features added at encoder level `skip_level` (1-based). Returns
        (output, u1 features, new hidden list)."""
        if hidden is None:
            hidden = self.init_hidden(x.shape[0], x.shape[-2], x.shape[-1], x)
        skips, new_hidden, y = [], [], x
        for j, level in enumerate(self.encoder):
            y = level(y, hidden[j], skip if j + 1 == self.skip_level else None)
            new_hidden.append(y)
            if j < self.levels:
                skips.append(y)
                y = F.max_pool2d(y, 2)
        for i, block in enumerate(self.decoder):
            j = self.levels - i  # this block is u_j
            y = F.interpolate(y, scale_factor=2, mode="nearest")
            y = block(y, skips[j - 1], conds[j - 1] if conds is not None else None)
        return self.out(y), y, new_hidden


def _he_init(model):
    """He (Kaiming) normal init for every conv weight, zero biases; CFM gamma/beta and deformable
    offset/mask generators keep their zero init so those modules start as identity / plain conv."""
    keep = set()
    for m in model.modules():
        if isinstance(m, CFM):
            keep.update((m.gamma, m.beta))
        if isinstance(m, DeformConv2d):
            keep.update(c for c in (m.offset_conv, m.mask_conv) if c is not None)
    for m in model.modules():
        if isinstance(m, (nn.Conv2d, DeformConv2d)) and m not in keep:
            nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)


class SRDNet(nn.Module):
    """End-to-end SR + denoising network; every ablation of the paper's tables is an argument.

    in_channels / gbuffer_channels / scale: model contract (ARCHITECTURE.md). channels: width of every
    conv (paper: 32). sr_blocks: ResBlocks in the SR stage (paper: 4). stage_order: "sr_dn" (paper) or
    "dn_sr". channel_aug: the first stage passes `channels` channels instead of 3. skip: inter-stage skip
    connection. gbuffer_mode: "cfm" or "concat". sr_deform_blocks / dn_deform_blocks: how many of the last
    SR ResBlocks / decoder blocks (u1, u2, ...) use a deformable conv2 (paper: 0 / 3). dilation: dilation
    of the SR ResBlocks' conv2 (Table 2 study). dn_levels: encoder levels (pooling steps) of the denoiser.
    intermediate: return the SR stage's RGB head (only for stage_order="sr_dn" with scale > 1).
    input_residual: every RGB image a stage makes is predicted, by a zero-initialised output conv, as a
    correction to the bilinear upsampling of that stage's RGB input (the previous stage's image without
    channel_aug, else the network input), so training starts at the "Input bilinear" row and the
    Cascade stages compose exactly like the end-to-end model. Not in
    the paper (which does not say); without it the network needs far more steps than the smoke and cpu
    scales give to catch up with bilinear. Set false for the paper's plain output. linear_base: the
    network domain's bench.hdr mode (e.g. "pu") to interpolate that base as linear radiance
    (bench.nn.upsampled_input); None interpolates the network-domain values. Only the dark_bias study
    sets it (conf/study/dark_bias.yaml, docs/studies.md).
    """

    recurrent = True

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, channels=32, sr_blocks=4,
                 stage_order="sr_dn", channel_aug=True, skip=True, gbuffer_mode="cfm",
                 sr_deform_blocks=0, dn_deform_blocks=3, dilation=1, dn_levels=5, intermediate=True,
                 cond_channels=16, input_residual=True, linear_base=None):
        super().__init__()
        if stage_order not in ("sr_dn", "dn_sr"):
            raise ValueError(f"stage_order must be 'sr_dn' or 'dn_sr', got {stage_order!r}")
        if gbuffer_mode not in ("cfm", "concat"):
            raise ValueError(f"gbuffer_mode must be 'cfm' or 'concat', got {gbuffer_mode!r}")
        if scale < 1 or scale & (scale - 1):
            raise ValueError(f"scale must be a power of two (the skip joins equal-size levels), got {scale}")
        if not 0 <= sr_deform_blocks <= sr_blocks:
            raise ValueError(f"sr_deform_blocks must be in 0..{sr_blocks}, got {sr_deform_blocks}")
        self.scale, self.stage_order, self.gbuffer_mode = scale, stage_order, gbuffer_mode
        self.gbuffer_channels, self.dn_levels = gbuffer_channels, dn_levels
        self.channel_aug, self.skip, self.input_residual = channel_aug, skip, input_residual
        self.base_domain = transforms(linear_base)
        self.mid_ch = channels if channel_aug else 3
        self.emit_intermediate = intermediate and stage_order == "sr_dn" and scale > 1
        use_cfm = gbuffer_mode == "cfm" and gbuffer_channels > 0
        cond_ch = cond_channels if use_cfm else 0
        concat_ch = gbuffer_channels if gbuffer_mode == "concat" else 0
        mid_ch = channels if channel_aug else 3  # channels passed from the first to the second stage
        # the LR-sized denoiser level, where the SR deep features are added (sr_dn)
        skip_level = (scale.bit_length() if stage_order == "sr_dn" else 0) if skip else 0

        self.cond_sr = ConditionNet(gbuffer_channels, cond_ch, channels) if use_cfm else None
        self.cond_dn = ConditionNet(gbuffer_channels, cond_ch, channels) if use_cfm else None
        if stage_order == "sr_dn":
            self.sr = SRStage(in_channels + concat_ch, mid_ch, channels, sr_blocks, scale, cond_ch,
                              sr_deform_blocks, dilation, rgb_head=channel_aug and self.emit_intermediate)
            self.dn = RecurrentDenoiser(mid_ch + concat_ch, 3, channels, dn_levels, cond_ch,
                                        dn_deform_blocks, skip_level)
        else:
            self.dn = RecurrentDenoiser(in_channels + concat_ch, mid_ch, channels, dn_levels, cond_ch,
                                        dn_deform_blocks, skip_level)
            self.sr = SRStage(mid_ch + concat_ch, channels, channels, sr_blocks, scale, cond_ch,
                              sr_deform_blocks, dilation, rgb_head=True)
        _he_init(self)
        if input_residual:
            for conv in self._image_convs():
                zero_init(conv)

    def _image_convs(self):
        """The convs whose output is an RGB image (a residual on the upsampled input)."""
        if self.stage_order == "sr_dn":
            convs = [self.dn.out] + ([self.sr.rgb] if self.sr.rgb is not None else [])
            return convs + ([self.sr.up.conv] if self.mid_ch == 3 else [])
        return [self.sr.rgb] + ([self.dn.out] if self.mid_ch == 3 else [])

    def _base(self, x, scale):
        """What an RGB output is a residual on: the bilinear-upsampled input, or 0."""
        return upsampled_input(x, scale, self.base_domain) if self.input_residual else 0

    # ---- geometry -------------------------------------------------------------------------------
    def _dn_factor(self):
        """Size of the denoiser's level 1 relative to the network input."""
        return self.scale if self.stage_order == "sr_dn" else 1

    def _pad_multiple(self):
        return max(1, (2 ** self.dn_levels) // self._dn_factor())

    def _pad(self, t, multiple=None):
        """Replicate-pad (B, C, h, w) at bottom/right to a multiple of `multiple` (default
        _pad_multiple()); zero-channel tensors just get the new size."""
        m = multiple or self._pad_multiple()
        ph, pw = -t.shape[-2] % m, -t.shape[-1] % m
        if (ph or pw) and t.shape[1] > 0:
            t = F.pad(t, (0, pw, 0, ph), mode="replicate")
        elif ph or pw:
            t = t.new_zeros(*t.shape[:-2], t.shape[-2] + ph, t.shape[-1] + pw)
        return t

    def _gbuffer(self, g, x):
        """The gBuffer prefix this model uses, as (B, G, h, w); an empty tensor shaped like x's batch and
        size when the model uses none or g is None."""
        if g is None or self.gbuffer_channels == 0:
            return x.new_zeros(x.shape[0], 0, *x.shape[-2:])
        return g[:, :self.gbuffer_channels]

    def _dn_conds(self, g, factor):
        """Per-decoder-level conditioning: ConditionNet at g's size, nearest-upsampled by `factor` to
        the denoiser's level 1, average-pooled by 2^(j-1) for level j."""
        if self.cond_dn is None:
            return None
        cond = self.cond_dn(g)
        if factor > 1:
            cond = F.interpolate(cond, scale_factor=factor, mode="nearest")
        return [cond if j == 0 else F.avg_pool2d(cond, 2 ** j) for j in range(self.dn_levels)]

    @staticmethod
    def _concat(x, g, factor=1):
        """Concatenate g (nearest-upsampled by factor) to x; a no-op when g has no channels."""
        if g.shape[1] == 0:
            return x
        if factor > 1:
            g = F.interpolate(g, scale_factor=factor, mode="nearest")
        return torch.cat((x, g), dim=1)

    # ---- streaming ------------------------------------------------------------------------------
    def init_state(self, x0):
        """Zero recurrent state for frames shaped like x0 ((B, C, h, w), or (B, T, C, h, w))."""
        b, h, w = x0.shape[0], x0.shape[-2], x0.shape[-1]
        m, f = self._pad_multiple(), self._dn_factor()
        height, width = (h + (-h % m)) * f, (w + (-w % m)) * f
        return {"hidden": self.dn.init_hidden(b, height, width, x0)}

    def step(self, x_t, g_t, state):
        """One frame: x_t (B, C, h, w), g_t (B, G, h, w) or None -> ({"final", ["intermediate"]}, state)."""
        h, w = x_t.shape[-2:]
        x = self._pad(x_t)
        g = self._pad(self._gbuffer(g_t, x_t))
        concat = self.gbuffer_mode == "concat"
        out = {}
        if self.stage_order == "sr_dn":
            cond = self.cond_sr(g) if self.cond_sr is not None else None
            feats, rgb, deep = self.sr(self._concat(x, g) if concat else x, cond)
            base = self._base(x, self.scale)
            if rgb is not None:
                rgb = rgb + base
            elif self.mid_ch == 3:
                feats = feats + base
            dn_in = self._concat(feats, g, self.scale) if concat else feats
            final, _, hidden = self.dn(dn_in, state["hidden"], self._dn_conds(g, self.scale),
                                       deep if self.skip else None)
            final = final + (feats if self.mid_ch == 3 and self.input_residual else base)
            if self.emit_intermediate:
                out["intermediate"] = (rgb if rgb is not None else feats)[..., :h * self.scale, :w * self.scale]
        else:
            dn_out, u1, hidden = self.dn(self._concat(x, g) if concat else x, state["hidden"],
                                         self._dn_conds(g, 1))
            if self.mid_ch == 3:
                dn_out = dn_out + self._base(x, 1)
            cond = self.cond_sr(g) if self.cond_sr is not None else None
            _, final, _ = self.sr(self._concat(dn_out, g) if concat else dn_out, cond,
                                  u1 if self.skip else None)
            final = final + self._base(dn_out if self.mid_ch == 3 else x, self.scale)
        out["final"] = final[..., :h * self.scale, :w * self.scale]
        return out, {"hidden": hidden}

    def forward(self, x, g=None):
        """x: (B, T, C, h, w), g: (B, T, G, h, w) -> dict of (B, T, 3, scale*h, scale*w); state starts at zero."""
        return run_sequence(self.init_state, self.step, x, g)

    # ---- cascade --------------------------------------------------------------------------------
    def forward_stage(self, stage, x, g=None):
        """Run ONE stage alone on a sequence, for Cascade training/evaluation. Returns {"final": ...}.

        stage_order="sr_dn": "sr": x = LR noisy -> HR noisy estimate (B, T, 3, 2h, 2w) (the RGB head);
                             "dn": x = HR noisy (B, T, 3, 2h, 2w) -> HR clean.
        stage_order="dn_sr": "dn": x = LR noisy -> LR clean; "sr": x = LR clean -> HR clean.
        g: the SR stage takes g at x's size. The denoiser takes g at x's size OR at the network-input
        (LR) size as the full model does (conditioning then brought up as in forward); the ratio of the
        sizes decides. Chaining the two stages with LR g reproduces forward exactly when no padding is
        needed. The stages exchange RGB images only, so this needs channel_aug=False and skip=False
        (the paper's Cascade rows have neither); otherwise it raises ValueError.
        """
        if stage not in ("sr", "dn"):
            raise ValueError(f"stage must be 'sr' or 'dn', got {stage!r}")
        if self.channel_aug or self.skip:
            raise ValueError("forward_stage needs channel_aug=False and skip=False (RGB between stages)")
        # hidden=None: the denoiser starts each sequence from zeros sized by its own input
        return run_sequence(lambda x0: {"hidden": None},
                             lambda x_t, g_t, s: self._stage_step(stage, x_t, g_t, s), x, g)

    def _stage_step(self, stage, x_t, g_t, state):
        """One frame of forward_stage; the denoiser's recurrent state is carried in `state`."""
        h, w = x_t.shape[-2:]
        concat = self.gbuffer_mode == "concat"
        if stage == "sr":
            x, g = self._pad(x_t), self._pad(self._gbuffer(g_t, x_t))
            cond = self.cond_sr(g) if self.cond_sr is not None else None
            feats, rgb, _ = self.sr(self._concat(x, g) if concat else x, cond)
            out = (feats if self.stage_order == "sr_dn" else rgb) + self._base(x, self.scale)
            return {"final": out[..., :h * self.scale, :w * self.scale]}, state
        factor = x_t.shape[-1] // g_t.shape[-1] if g_t is not None else 1  # x size / g size
        multiple = 2 ** self.dn_levels
        x = self._pad(x_t, multiple)
        g = self._pad(self._gbuffer(g_t, x_t[..., ::factor, ::factor]), max(1, multiple // factor))
        out, _, hidden = self.dn(self._concat(x, g, factor) if concat else x, state["hidden"],
                                 self._dn_conds(g, factor))
        out = out + self._base(x, 1)
        return {"final": out[..., :h, :w]}, {"hidden": hidden}


class SRDStage(nn.Module):
    """One stage of an SRDNet on its own, for Cascade training: forward(x, g) = net.forward_stage(stage, x, g).
    Its state dict is the whole net's under `net.`; `SRDNet.load_stage` takes that stage's part back."""

    recurrent = True

    def __init__(self, net: SRDNet, stage: str):
        super().__init__()
        self.net, self.stage = net, stage

    def forward(self, x, g=None):
        return self.net.forward_stage(self.stage, x, g)


def _stage_prefixes(stage):
    return ("sr.", "cond_sr.") if stage == "sr" else ("dn.", "cond_dn.")


def load_stage(net: SRDNet, stage: str, stage_state: dict) -> SRDNet:
    """Copy the parameters of `stage` ("sr" or "dn") from an SRDStage's state dict into `net` (in place):
    a Cascade is two separately trained stages assembled into one net."""
    prefixes = _stage_prefixes(stage)
    part = {k[len("net."):]: v for k, v in stage_state.items() if k[len("net."):].startswith(prefixes)}
    if not part:
        raise ValueError(f"no parameters of stage {stage!r} in the given state dict")
    # missing keys as a load sees them, found on a copy so that `net` is left as it was when the state does not fit
    missing = [k for k in copy.deepcopy(net).load_state_dict(part, strict=False).missing_keys
               if k.startswith(prefixes)]
    if missing:
        raise ValueError(f"stage {stage!r} state lacks {missing[:3]}...")
    net.load_state_dict(part, strict=False)
    return net


"""VGG16 feature extractor for the perceptual loss (Johnson et al. 2016), in plain PyTorch.

The layers and their indices match torchvision's `vgg16().features`, so torchvision state dicts load
directly ('0.weight', '2.weight', ... or 'features.0.weight'; classifier keys are ignored). No weights
are shipped or downloaded: callers load a file with `load_vgg16_features`, or opt in explicitly to a
fixed-seed random network with `random_vgg16_features`.
"""
import torch
import torch.nn as nn

# torchvision's vgg16 configuration "D": channel counts, "M" = 2x2 max-pool.
_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _layer_names():
    """Names of torchvision's vgg16().features modules in order: conv1_1, relu1_1, ..., pool5."""
    names, block, index = [], 1, 1
    for v in _CFG:
        if v == "M":
            names.append(f"pool{block}")
            block, index = block + 1, 1
        else:
            names += [f"conv{block}_{index}", f"relu{block}_{index}"]
            index += 1
    return names


LAYER_NAMES = _layer_names()


def _build_features(last_index):
    """nn.Sequential of torchvision's vgg16().features modules 0..last_index (same indices)."""
    layers, in_ch = [], 3
    for v in _CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(in_ch, v, 3, padding=1), nn.ReLU(inplace=True)]
            in_ch = v
    return nn.Sequential(*layers[:last_index + 1])


class VGG16Features(nn.Module):
    """VGG16 `features` up to and including `layer` (e.g. "relu3_3"); input RGB in [0, 1].

    ImageNet mean/std normalization happens inside. Parameters are frozen (requires_grad=False) and the
    module stays in eval mode; gradients still flow to the input, as a perceptual loss needs.
    """

    def __init__(self, layer="relu3_3"):
        super().__init__()
        if layer not in LAYER_NAMES:
            raise ValueError(f"unknown VGG16 layer {layer!r}; choose one of {LAYER_NAMES}")
        self.layer = layer
        self.features = _build_features(LAYER_NAMES.index(layer))
        # non-persistent: the state dict holds exactly torchvision's 'features.*' keys
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode=True):
        """Always eval: the extractor is a fixed loss network."""
        return super().train(False)

    def forward(self, x):
        return self.features((x - self.mean) / self.std)


def load_vgg16_features(path, layer="relu3_3"):
    """VGG16Features up to `layer` with weights from a torchvision-format state dict file.

    Accepts keys '0.weight' or 'features.0.weight' (the full torchvision vgg16 file works; its
    classifier is ignored). Raises ValueError naming the missing keys if the file stops before `layer`.
    """
    state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a state dict, got {type(state).__name__}")
    state = {k[len("features."):] if k.startswith("features.") else k: v for k, v in state.items()}
    model = VGG16Features(layer)
    needed = model.features.state_dict().keys()
    missing = [k for k in needed if k not in state]
    if missing:
        raise ValueError(f"{path} lacks VGG16 weights needed up to {layer}: missing {missing}")
    model.features.load_state_dict({k: state[k] for k in needed})
    return model


def random_vgg16_features(layer, seed=0):
    """VGG16Features with a fixed-seed random (Kaiming) initialization; explicit opt-in only, for runs
    and tests without pretrained weights. Not a perceptual metric in any meaningful sense."""
    generator_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        model = VGG16Features(layer)
        for m in model.features:
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
    finally:
        torch.random.set_rng_state(generator_state)
    return model

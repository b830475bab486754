"""Shared layers: CFM, deformable conv, residual blocks, the EDSR trunk, the recurrence, VGG16 features (floor 1: no project imports)."""
from .blocks import (EDSRTrunk, PixelShuffleUp, RecurrentBlock, ResBlock, RGBUpsampler, bilinear, conv3x3,
                     run_sequence, upsampled_input, zero_init)
from .cfm import CFM, ConditionNet
from .deform import (DeformConv2d, deform_conv2d, eager_gather, grid_sample_training, inference_sampler,
                     training_sampler)
from .vgg import VGG16Features, load_vgg16_features, random_vgg16_features

__all__ = ["CFM", "ConditionNet", "DeformConv2d", "EDSRTrunk", "PixelShuffleUp", "RecurrentBlock", "ResBlock", "RGBUpsampler",
           "VGG16Features", "bilinear", "conv3x3", "deform_conv2d", "eager_gather", "grid_sample_training", "inference_sampler", "training_sampler", "run_sequence", "upsampled_input", "zero_init", "load_vgg16_features", "random_vgg16_features"]

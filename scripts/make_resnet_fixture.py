#!/usr/bin/env python3
"""Reference fixture for the occ-model image encoder (crates/model/src/{backbone,fpn,weights}.rs).

Builds ResNets with exactly the torchvision module layout (conv1 7x7/2 + bn1 + relu + maxpool 3x3/2 pad 1,
layer1..layer4 of BasicBlock or Bottleneck "v1.5" with the stride on the 3x3 conv, downsample = 1x1 conv + BN as
`downsample.0` / `downsample.1`, avgpool + fc) in plain torch (torchvision is not needed), but with a reduced stem
width `base_width` (torchvision's is 64) so the files stay small. Also an mmdet-style FPN (lateral 1x1 convs with
bias, top-down nearest upsampling to the finer level's size + add, 3x3 output convs with bias, no extra levels).

Weights are random but seeded and non-trivial (BN running statistics and affine parameters are random too) and are
stored as float32; the reference outputs are computed in float64 from exactly those float32 values, in eval mode.

Writes into crates/model/tests/data/resnet_tiny/ (or the folder given as the first argument):
  manifest.json                    cases, files and shapes (the Rust tests read this, not file names)
  <case>.pth                       torch.save(state_dict) (PyTorch zip format; includes fc.* and
                                   num_batches_tracked, which the loader must ignore)
  <case>.safetensors               the same state dict, written by the small writer below
  <case>_<H>x<W>_input.npy         float32 [1,3,H,W] input
  <case>_<H>x<W>_layer{1..4}.npy   float32 outputs of layer1..layer4 (strides 4, 8, 16, 32)
  <case>_fpn<C>.safetensors        (cases with an FPN) FPN weights (keys lateral_convs.i.*, fpn_convs.i.*)
  <case>_fpn<C>_checkpoint.pth     the same, nested: {"meta": {...}, "state_dict": {...}}
  <case>_<H>x<W>_fpn<C>_out{i}.npy FPN outputs for the case's last input

Run: /root/venv-ref/bin/python scripts/make_resnet_fixture.py
"""

import json
import os
import struct
import sys

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, inplanes, planes, stride=1, downsample=None):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, inplanes, planes, stride=1, downsample=None):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, 1, 0, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, 1, 0, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


ARCH = {18: (BasicBlock, [2, 2, 2, 2]), 34: (BasicBlock, [3, 4, 6, 3]), 50: (Bottleneck, [3, 4, 6, 3])}


class ResNet(nn.Module):
    def __init__(self, depth, base_width, num_classes=10):
        super().__init__()
        block, layers = ARCH[depth]
        self.inplanes = base_width
        self.conv1 = nn.Conv2d(3, base_width, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(base_width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block, base_width, layers[0], 1)
        self.layer2 = self._make_layer(block, base_width * 2, layers[1], 2)
        self.layer3 = self._make_layer(block, base_width * 4, layers[2], 2)
        self.layer4 = self._make_layer(block, base_width * 8, layers[3], 2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(base_width * 8 * block.expansion, num_classes)

    def _make_layer(self, block, planes, blocks, stride):
        downsample = None
        if stride != 1 or self.inplanes != planes * block.expansion:
            downsample = nn.Sequential(
                nn.Conv2d(self.inplanes, planes * block.expansion, 1, stride, 0, bias=False),
                nn.BatchNorm2d(planes * block.expansion),
            )
        mods = [block(self.inplanes, planes, stride, downsample)]
        self.inplanes = planes * block.expansion
        for _ in range(1, blocks):
            mods.append(block(self.inplanes, planes))
        return nn.Sequential(*mods)

    def stages(self, x):
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        outs = []
        for layer in (self.layer1, self.layer2, self.layer3, self.layer4):
            x = layer(x)
            outs.append(x)
        return outs


class Fpn(nn.Module):
    """mmdet FPN with start_level 0, no extra levels, no norm: field names match occ-model's `Fpn`."""

    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.lateral_convs = nn.ModuleList([nn.Conv2d(c, out_channels, 1) for c in in_channels])
        self.fpn_convs = nn.ModuleList([nn.Conv2d(out_channels, out_channels, 3, padding=1) for _ in in_channels])

    def forward(self, inputs):
        laterals = [conv(x) for conv, x in zip(self.lateral_convs, inputs)]
        for i in range(len(laterals) - 1, 0, -1):
            laterals[i - 1] = laterals[i - 1] + F.interpolate(laterals[i], size=laterals[i - 1].shape[2:], mode="nearest")
        return [conv(x) for conv, x in zip(self.fpn_convs, laterals)]


def randomise(module, gen):
    """Seeded, non-trivial parameters: conv ~ kaiming normal (fan_out, relu), BN affine/statistics random."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            fan_out = m.out_channels * m.kernel_size[0] * m.kernel_size[1]
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=gen) * (2.0 / fan_out) ** 0.5)
                if m.bias is not None:
                    m.bias.copy_(torch.randn(m.bias.shape, generator=gen) * 0.1)
        elif isinstance(m, nn.BatchNorm2d):
            c = m.num_features
            with torch.no_grad():
                m.weight.copy_(0.3 + 0.5 * torch.rand(c, generator=gen))
                m.bias.copy_(torch.randn(c, generator=gen) * 0.1)
                m.running_mean.copy_(torch.randn(c, generator=gen) * 0.1)
                m.running_var.copy_(0.5 + torch.rand(c, generator=gen))
                m.num_batches_tracked.fill_(7)
        elif isinstance(m, nn.Linear):
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=gen) * 0.1)
                m.bias.zero_()


SAFETENSORS_DTYPE = {torch.float32: ("F32", "<f4"), torch.int64: ("I64", "<i8"), torch.float64: ("F64", "<f8")}


def write_safetensors(path, state):
    """Minimal safetensors writer: u64 LE header length, JSON header (padded with spaces to 8 bytes), raw LE data."""
    header, blobs, offset = {}, [], 0
    for name, t in state.items():
        dtype, np_dtype = SAFETENSORS_DTYPE[t.dtype]
        data = t.detach().cpu().contiguous().numpy().astype(np_dtype).tobytes()
        header[name] = {"dtype": dtype, "shape": list(t.shape), "data_offsets": [offset, offset + len(data)]}
        blobs.append(data)
        offset += len(data)
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * ((8 - len(raw) % 8) % 8)
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(struct.pack("<Q", len(raw)))
        f.write(raw)
        for b in blobs:
            f.write(b)
    os.replace(tmp, path)


def save_npy(path, array):
    tmp = path + ".tmp.npy"
    np.save(tmp, np.ascontiguousarray(array, dtype=np.float32))
    os.replace(tmp, path)


def save_pth(path, state):
    tmp = path + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, path)


CASES = [
    # name, depth, base_width, weight formats, seed, inputs ([H, W]), FPN out channels (applied to the last input)
    ("resnet18_w4", 18, 4, ["pth", "safetensors"], 1, [[64, 96], [70, 90]], 8),
    ("resnet50_w2", 50, 2, ["safetensors"], 2, [[64, 96]], None),
]


def main():
    out_dir = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "..", "crates", "model", "tests", "data", "resnet_tiny")
    os.makedirs(out_dir, exist_ok=True)
    torch.use_deterministic_algorithms(True)
    manifest = {"generator": "scripts/make_resnet_fixture.py", "torch": torch.__version__, "cases": []}
    for name, depth, base_width, formats, seed, inputs, fpn_out in CASES:
        gen = torch.Generator().manual_seed(seed)
        model = ResNet(depth, base_width)
        randomise(model, gen)
        model.eval()
        state = model.state_dict()
        case = {"name": name, "depth": depth, "base_width": base_width, "weights": [], "runs": []}
        if "pth" in formats:
            case["weights"].append(f"{name}.pth")
            save_pth(os.path.join(out_dir, f"{name}.pth"), state)
        if "safetensors" in formats:
            case["weights"].append(f"{name}.safetensors")
            write_safetensors(os.path.join(out_dir, f"{name}.safetensors"), state)
        model = model.double()
        for hw in inputs:
            tag = f"{name}_{hw[0]}x{hw[1]}"
            x = torch.randn([1, 3] + hw, generator=gen, dtype=torch.float32)
            with torch.no_grad():
                outs = model.stages(x.double())
            run = {"input": f"{tag}_input.npy", "input_shape": [1, 3] + hw, "strides": [4, 8, 16, 32], "stages": []}
            save_npy(os.path.join(out_dir, run["input"]), x.numpy())
            for i, o in enumerate(outs):
                fname = f"{tag}_layer{i + 1}.npy"
                save_npy(os.path.join(out_dir, fname), o.numpy())
                run["stages"].append({"file": fname, "shape": list(o.shape)})
            case["runs"].append(run)
            print(tag, "params", sum(v.numel() for v in state.values()),
                  "max |stage|", [round(float(o.abs().max()), 3) for o in outs])
        if fpn_out is not None:
            fpn = Fpn([o.shape[1] for o in outs], fpn_out)
            randomise(fpn, gen)
            fpn.eval()
            fname = f"{name}_fpn{fpn_out}.safetensors"
            write_safetensors(os.path.join(out_dir, fname), fpn.state_dict())
            with torch.no_grad():
                fouts = fpn.double()(outs)
            # The same weights nested like a training checkpoint (top-level key "state_dict" + metadata).
            nested = f"{name}_fpn{fpn_out}_checkpoint.pth"
            save_pth(os.path.join(out_dir, nested),
                     {"meta": {"epoch": 3, "note": "fixture"}, "state_dict": fpn.state_dict()})
            fpn_entry = {"out_channels": fpn_out, "weights": fname, "checkpoint": nested,
                         "checkpoint_top_level_key": "state_dict", "run": len(case["runs"]) - 1, "outputs": []}
            for i, o in enumerate(fouts):
                fname = f"{tag}_fpn{fpn_out}_out{i}.npy"
                save_npy(os.path.join(out_dir, fname), o.numpy())
                fpn_entry["outputs"].append({"file": fname, "shape": list(o.shape)})
            case["fpn"] = fpn_entry
            print(tag, "fpn max", [round(float(o.abs().max()), 3) for o in fouts])
        manifest["cases"].append(case)
    tmp = os.path.join(out_dir, "manifest.json.tmp")
    with open(tmp, "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    os.replace(tmp, os.path.join(out_dir, "manifest.json"))
    total = sum(os.path.getsize(os.path.join(out_dir, f)) for f in os.listdir(out_dir))
    print("total bytes", total)


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Reference outputs of diffusers' own UNet2DConditionModel and AutoencoderKL, for the test
that checks extranerf's burn models against diffusers (tests/diffusion_golden.rs).

Writes, under OUT (default tests/fixtures/diffusers_tiny):
  unet_conv/   a tiny inpainting U-Net (1x1-conv projections, odd head layout) in diffusers'
               save_pretrained layout: config.json + diffusion_pytorch_model.safetensors
  unet_linear/ the same with use_linear_projection and per-block heads (SD 2 style)
  vae/         a tiny AutoencoderKL
  clip_quick/, clip_gelu/  tiny transformers CLIPTextModels (quick_gelu and gelu)
  tokenizer/   a tiny CLIP BPE vocabulary (byte symbols plus merges learnt from a few words)
  golden.safetensors  inputs and the reference outputs (f32; token ids as f32)

The models are random (seeded); nothing here comes from pretrained weights. Run it once with
diffusers and torch installed (CPU is enough):

  pip install --target /tmp/pyref torch==2.5.1 diffusers==0.31.0 safetensors
  PYTHONPATH=/tmp/pyref python3 tools/diffusers_golden.py
"""

import sys
from pathlib import Path

import json
from collections import Counter

import torch
from diffusers import AutoencoderKL, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer
from safetensors.torch import save_file


def tiny_unet(linear: bool) -> UNet2DConditionModel:
    return UNet2DConditionModel(
        sample_size=8,
        in_channels=9,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        block_out_channels=(8, 16),
        layers_per_block=1,
        norm_num_groups=4,
        cross_attention_dim=12,
        attention_head_dim=(2, 4) if linear else 2,
        use_linear_projection=linear,
    )


def tiny_unet_odd() -> UNet2DConditionModel:
    # The paths the other two leave out: per-block layer lists, two transformer layers, no
    # middle block, a frequency shift, a centred input, a three-level layout.
    return UNet2DConditionModel(
        sample_size=8,
        in_channels=9,
        out_channels=4,
        center_input_sample=True,
        freq_shift=1,
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"),
        mid_block_type=None,
        block_out_channels=(8, 16, 16),
        layers_per_block=(1, 2, 1),
        transformer_layers_per_block=(1, 2, 1),
        norm_num_groups=4,
        cross_attention_dim=12,
        attention_head_dim=(2, 4, 2),
    )


def tiny_vae() -> AutoencoderKL:
    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        block_out_channels=(8, 16),
        layers_per_block=1,
        latent_channels=4,
        norm_num_groups=4,
    )


PROMPTS = ["a photo of sks scene", "The  fern's leaves, 2024!"]
CORPUS = "a photo of sks scene with the fern and its leaves photo scene fern fern's"


def bytes_to_unicode():
    bs = list(range(33, 127)) + list(range(161, 173)) + list(range(174, 256))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def tiny_tokenizer(out: Path) -> CLIPTokenizer:
    symbols = list(bytes_to_unicode().values())
    vocab = symbols + [s + "</w>" for s in symbols]
    words = [list(w[:-1]) + [w[-1] + "</w>"] for w in CORPUS.split()]
    merges = []
    for _ in range(40):
        pairs = Counter(p for w in words for p in zip(w, w[1:]))
        if not pairs:
            break
        (a, b), _ = pairs.most_common(1)[0]
        merges.append(f"{a} {b}")
        vocab.append(a + b)
        merged = []
        for w in words:
            i, nw = 0, []
            while i < len(w):
                if i + 1 < len(w) and (w[i], w[i + 1]) == (a, b):
                    nw.append(a + b)
                    i += 2
                else:
                    nw.append(w[i])
                    i += 1
            merged.append(nw)
        words = merged
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    out.mkdir(parents=True, exist_ok=True)
    (out / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(vocab)}))
    (out / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n")
    tok = CLIPTokenizer(str(out / "vocab.json"), str(out / "merges.txt"))
    tok.save_pretrained(out)
    return tok


def randomize(model: torch.nn.Module, gen: torch.Generator) -> None:
    # Default inits leave zeros (biases, GroupNorm betas) that would hide layout errors.
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.2)


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "tests/fixtures/diffusers_tiny")
    out.mkdir(parents=True, exist_ok=True)
    gen = torch.Generator().manual_seed(1234)
    torch.manual_seed(1234)
    golden = {}
    # Odd spatial size: the up block must upsample to the skip's size.
    sample = torch.randn(2, 9, 9, 13, generator=gen)
    context = torch.randn(2, 3, 12, generator=gen)
    timesteps = torch.tensor([10.0, 700.0])
    golden["unet.sample"] = sample
    golden["unet.context"] = context
    golden["unet.timesteps"] = timesteps
    for name, make in (
        ("unet_conv", lambda: tiny_unet(False)),
        ("unet_linear", lambda: tiny_unet(True)),
        ("unet_odd", tiny_unet_odd),
    ):
        unet = make().eval()
        randomize(unet, gen)
        unet.save_pretrained(out / name, safe_serialization=True)
        with torch.no_grad():
            golden[f"{name}.out"] = unet(sample, timesteps, context).sample
    vae = tiny_vae().eval()
    randomize(vae, gen)
    vae.save_pretrained(out / "vae", safe_serialization=True)
    image = torch.rand(1, 3, 12, 16, generator=gen) * 2 - 1
    with torch.no_grad():
        post = vae.encode(image).latent_dist
        golden["vae.image"] = image
        golden["vae.mean"] = post.mean
        golden["vae.logvar"] = post.logvar
        golden["vae.decoded"] = vae.decode(post.mean).sample
    # The same VAE as an older checkpoint: fp16 tensors and the deprecated attention names
    # (query/key/value/proj_attn) that diffusers still converts on load.
    old = out / "vae_old_fp16"
    old.mkdir(parents=True, exist_ok=True)
    (old / "config.json").write_text((out / "vae" / "config.json").read_text())
    renamed = {}
    for k, v in vae.state_dict().items():
        for new, dep in ((".to_q.", ".query."), (".to_k.", ".key."), (".to_v.", ".value."), (".to_out.0.", ".proj_attn.")):
            if "attentions" in k:
                k = k.replace(new, dep)
        renamed[k] = v.half().contiguous()
    save_file(renamed, old / "diffusion_pytorch_model.safetensors")
    tok = tiny_tokenizer(out / "tokenizer")
    ids = tok(PROMPTS, padding="max_length", max_length=12, truncation=True, return_tensors="pt").input_ids
    golden["clip.ids"] = ids.float()
    for name, act in (("clip_quick", "quick_gelu"), ("clip_gelu", "gelu")):
        cfg = CLIPTextConfig(
            vocab_size=len(tok.get_vocab()),
            hidden_size=12,
            intermediate_size=32,
            num_hidden_layers=2,
            num_attention_heads=2,
            max_position_embeddings=12,
            hidden_act=act,
            bos_token_id=tok.bos_token_id,
            eos_token_id=tok.eos_token_id,
            pad_token_id=tok.pad_token_id,
        )
        clip = CLIPTextModel(cfg).eval()
        randomize(clip, gen)
        clip.save_pretrained(out / name, safe_serialization=True)
        with torch.no_grad():
            golden[f"{name}.hidden"] = clip(ids).last_hidden_state
    save_file({k: v.contiguous().float() for k, v in golden.items()}, out / "golden.safetensors")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

//! CLIP's text encoder (transformers' `CLIPTextModel`) and its byte-level BPE tokenizer, for
//! Stable Diffusion folders that have `text_encoder/` and `tokenizer/`.
//!
//! Parameter names are transformers' (`text_model.embeddings.token_embedding`,
//! `text_model.encoder.layers.{i}.self_attn.q_proj`, `text_model.final_layer_norm`, ...). The
//! output is the last hidden state after the final LayerNorm, which is what SD conditions on
//! (SD 2's folders already drop the last layer in `num_hidden_layers`).

use std::collections::HashMap;
use std::path::Path;

use burn::module::{Module, Param};
use burn::nn::{Initializer, LayerNorm, LayerNormConfig};
use burn::tensor::activation::{gelu, sigmoid};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

use crate::blocks::multi_head_attention;
use crate::layers::Linear;
use crate::{DiffusionError, Result};

fn d_act() -> String {
    "quick_gelu".into()
}
fn d_eps() -> f64 {
    1e-5
}

/// transformers' `CLIPTextConfig` (the fields that define the network; other keys of
/// transformers' generic config are accepted and ignored).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClipTextConfig {
    /// Vocabulary size.
    pub vocab_size: usize,
    /// Width.
    pub hidden_size: usize,
    /// MLP width.
    pub intermediate_size: usize,
    /// Layers.
    pub num_hidden_layers: usize,
    /// Heads.
    pub num_attention_heads: usize,
    /// Context length (77).
    pub max_position_embeddings: usize,
    /// "quick_gelu" (OpenAI CLIP, SD 1.x) or "gelu" (OpenCLIP, SD 2).
    #[serde(default = "d_act")]
    pub hidden_act: String,
    /// LayerNorm epsilon.
    #[serde(default = "d_eps")]
    pub layer_norm_eps: f64,
    /// Everything else.
    #[serde(flatten)]
    pub other: Map<String, Value>,
}

impl ClipTextConfig {
    /// Reads and checks `text_encoder/config.json`.
    pub fn from_file(path: &Path) -> Result<ClipTextConfig> {
        let c: ClipTextConfig = crate::config::read_json(path)?;
        c.validate().map_err(|problem| DiffusionError::Config {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(c)
    }

    /// Checks the fields this implementation models.
    pub fn validate(&self) -> std::result::Result<(), String> {
        if let Some(a) = self.other.get("architectures").and_then(|a| a.as_array()) {
            if !a.iter().any(|v| v == "CLIPTextModel") {
                return Err(format!(
                    "architectures {a:?} does not include CLIPTextModel"
                ));
            }
        }
        if self.hidden_act != "quick_gelu" && self.hidden_act != "gelu" {
            return Err(format!(
                "hidden_act = {:?} is not supported (supported: quick_gelu, gelu)",
                self.hidden_act
            ));
        }
        if self.num_attention_heads == 0
            || !self.hidden_size.is_multiple_of(self.num_attention_heads)
        {
            return Err(format!(
                "hidden_size {} is not a multiple of num_attention_heads {}",
                self.hidden_size, self.num_attention_heads
            ));
        }
        if self.vocab_size == 0
            || self.max_position_embeddings == 0
            || self.num_hidden_layers == 0
            || self.intermediate_size == 0
        {
            return Err("vocab_size, max_position_embeddings, num_hidden_layers and intermediate_size must be > 0".into());
        }
        Ok(())
    }
}

/// transformers' `CLIPAttention`.
#[derive(Module, Debug)]
pub struct ClipAttention {
    /// Query.
    pub q_proj: Linear,
    /// Key.
    pub k_proj: Linear,
    /// Value.
    pub v_proj: Linear,
    /// Output.
    pub out_proj: Linear,
    /// Heads.
    pub heads: usize,
}

/// transformers' `CLIPMLP`.
#[derive(Module, Debug)]
pub struct ClipMlp {
    /// In.
    pub fc1: Linear,
    /// Out.
    pub fc2: Linear,
    /// quick_gelu when true, else exact gelu.
    pub quick_gelu: bool,
}

/// One pre-norm transformer layer.
#[derive(Module, Debug)]
pub struct ClipEncoderLayer {
    /// Causal self-attention.
    pub self_attn: ClipAttention,
    /// Before attention.
    pub layer_norm1: LayerNorm,
    /// MLP.
    pub mlp: ClipMlp,
    /// Before the MLP.
    pub layer_norm2: LayerNorm,
}

/// Token and position embeddings.
#[derive(Module, Debug)]
pub struct ClipEmbeddings {
    /// `[vocab, hidden]`.
    pub token_embedding: Embedding,
    /// `[positions, hidden]`.
    pub position_embedding: Embedding,
}

/// An embedding table with PyTorch's `weight` name and layout.
#[derive(Module, Debug)]
pub struct Embedding {
    /// `[n, dim]`.
    pub weight: Param<Tensor<2>>,
}

/// The encoder's layers.
#[derive(Module, Debug)]
pub struct ClipEncoder {
    /// Layers.
    pub layers: Vec<ClipEncoderLayer>,
}

/// `text_model` of transformers' CLIPTextModel.
#[derive(Module, Debug)]
pub struct ClipTextTransformer {
    /// Embeddings.
    pub embeddings: ClipEmbeddings,
    /// Layers.
    pub encoder: ClipEncoder,
    /// Final LayerNorm.
    pub final_layer_norm: LayerNorm,
}

/// CLIPTextModel.
#[derive(Module, Debug)]
pub struct ClipTextModel {
    /// The transformer.
    pub text_model: ClipTextTransformer,
}

impl ClipTextModel {
    /// A model of a validated config (lazy parameters).
    pub fn new(c: &ClipTextConfig, device: &Device) -> Result<ClipTextModel> {
        c.validate().map_err(DiffusionError::InvalidConfig)?;
        let d = c.hidden_size;
        let ln = || {
            LayerNormConfig::new(d)
                .with_epsilon(c.layer_norm_eps)
                .init(device)
        };
        let emb = |n: usize| Embedding {
            weight: Initializer::Normal {
                mean: 0.0,
                std: 0.02,
            }
            .init([n, d], device),
        };
        Ok(ClipTextModel {
            text_model: ClipTextTransformer {
                embeddings: ClipEmbeddings {
                    token_embedding: emb(c.vocab_size),
                    position_embedding: emb(c.max_position_embeddings),
                },
                encoder: ClipEncoder {
                    layers: (0..c.num_hidden_layers)
                        .map(|_| ClipEncoderLayer {
                            self_attn: ClipAttention {
                                q_proj: Linear::new(d, d, true, device),
                                k_proj: Linear::new(d, d, true, device),
                                v_proj: Linear::new(d, d, true, device),
                                out_proj: Linear::new(d, d, true, device),
                                heads: c.num_attention_heads,
                            },
                            layer_norm1: ln(),
                            mlp: ClipMlp {
                                fc1: Linear::new(d, c.intermediate_size, true, device),
                                fc2: Linear::new(c.intermediate_size, d, true, device),
                                quick_gelu: c.hidden_act == "quick_gelu",
                            },
                            layer_norm2: ln(),
                        })
                        .collect(),
                },
                final_layer_norm: ln(),
            },
        })
    }

    /// Context length.
    pub fn max_len(&self) -> usize {
        self.text_model
            .embeddings
            .position_embedding
            .weight
            .lazy_shape()[0]
    }

    /// Token ids `[b][l]` (l <= max_len) -> last hidden state `[b, l, hidden]`.
    pub fn forward(&self, ids: &[Vec<u32>], device: &Device) -> Result<Tensor<3>> {
        let b = ids.len();
        let l = ids.first().map_or(0, Vec::len);
        if b == 0 || l == 0 || l > self.max_len() || ids.iter().any(|r| r.len() != l) {
            return Err(DiffusionError::Input(format!(
                "CLIP input: {b} rows of {l} tokens (rows must be equal and at most {} long)",
                self.max_len()
            )));
        }
        let vocab = self
            .text_model
            .embeddings
            .token_embedding
            .weight
            .lazy_shape()[0];
        if let Some(t) = ids.iter().flatten().find(|t| **t as usize >= vocab) {
            return Err(DiffusionError::Input(format!(
                "token id {t} is outside the {vocab}-token vocabulary"
            )));
        }
        let flat: Vec<i64> = ids.iter().flatten().map(|&t| t as i64).collect();
        let idx = Tensor::<2, Int>::from_data(TensorData::new(flat, [b, l]), device);
        let e = &self.text_model.embeddings;
        let tok = burn::tensor::module::embedding(e.token_embedding.weight.val(), idx);
        let pos = e
            .position_embedding
            .weight
            .val()
            .narrow(0, 0, l)
            .unsqueeze::<3>();
        let mut h = tok + pos;
        // Causal mask: query i sees keys j <= i.
        let causal: Vec<bool> = (0..l * l).map(|k| k % l > k / l).collect();
        for layer in &self.text_model.encoder.layers {
            let heads = layer.self_attn.heads;
            let mask =
                Tensor::<1, Bool>::from_data(TensorData::new(causal.clone(), [l * l]), device)
                    .reshape([1, 1, l, l])
                    .expand([b, heads, l, l]);
            let a = &layer.self_attn;
            let x = layer.layer_norm1.forward(h.clone());
            let o = multi_head_attention(
                a.q_proj.forward(x.clone()),
                a.k_proj.forward(x.clone()),
                a.v_proj.forward(x),
                heads,
                Some(mask),
            );
            h = h + a.out_proj.forward(o);
            let x = layer.mlp.fc1.forward(layer.layer_norm2.forward(h.clone()));
            let x = if layer.mlp.quick_gelu {
                x.clone() * sigmoid(x * 1.702)
            } else {
                gelu(x)
            };
            h = h + layer.mlp.fc2.forward(x);
        }
        Ok(self.text_model.final_layer_norm.forward(h))
    }
}

/// Loads `dir/config.json` and `dir/model.safetensors` (transformers layout).
pub fn load_text_encoder(dir: &Path, device: &Device) -> Result<(ClipTextConfig, ClipTextModel)> {
    let config = ClipTextConfig::from_file(&dir.join("config.json"))?;
    let file = crate::weights::find_weights(dir, &["model.safetensors", "model.fp16.safetensors"])?;
    let mut m = ClipTextModel::new(&config, device)?;
    // Older exports carry the position_ids buffer, which is not a parameter.
    crate::weights::load_into(&mut m, &file, &[], &["position_ids"])?;
    Ok((config, m))
}

/// CLIP's byte-level BPE tokenizer (`tokenizer/vocab.json` + `tokenizer/merges.txt`): lower
/// case, whitespace collapsed, words split as CLIP's pattern does (contractions, letter runs,
/// single digits, runs of other symbols), each word's last symbol marked `</w>`.
#[derive(Clone, Debug)]
pub struct ClipTokenizer {
    vocab: HashMap<String, u32>,
    ranks: HashMap<(String, String), usize>,
    byte_char: [char; 256],
    /// Start token id.
    pub bos: u32,
    /// End token id.
    pub eos: u32,
    /// Padding id.
    pub pad: u32,
}

fn bytes_to_unicode() -> [char; 256] {
    let mut out = ['\0'; 256];
    let mut n = 0u32;
    for b in 0..256u32 {
        let printable =
            (33..=126).contains(&b) || (161..=172).contains(&b) || (174..=255).contains(&b);
        out[b as usize] = if printable {
            char::from_u32(b).unwrap_or('?')
        } else {
            n += 1;
            char::from_u32(255 + n).unwrap_or('?')
        };
    }
    out
}

impl ClipTokenizer {
    /// Reads a `tokenizer/` folder.
    pub fn load(dir: &Path) -> Result<ClipTokenizer> {
        let vpath = dir.join("vocab.json");
        let vocab: HashMap<String, u32> = crate::config::read_json(&vpath)?;
        let mpath = dir.join("merges.txt");
        let text = std::fs::read_to_string(&mpath).map_err(|e| DiffusionError::io(&mpath, e))?;
        let mut ranks = HashMap::new();
        for (i, line) in text
            .lines()
            .filter(|l| !l.starts_with("#version") && !l.trim().is_empty())
            .enumerate()
        {
            let mut parts = line.split(' ');
            match (parts.next(), parts.next(), parts.next()) {
                (Some(a), Some(b), None) => {
                    ranks.insert((a.to_string(), b.to_string()), i);
                }
                _ => {
                    return Err(DiffusionError::Config {
                        path: mpath,
                        problem: format!("merge {} is not two symbols: {line:?}", i + 1),
                    })
                }
            }
        }
        let id = |t: &str| {
            vocab.get(t).copied().ok_or_else(|| DiffusionError::Config {
                path: vpath.clone(),
                problem: format!("the vocabulary has no {t:?}"),
            })
        };
        let bos = id("<|startoftext|>")?;
        let eos = id("<|endoftext|>")?;
        // SD 2's tokenizer pads with "!" (special_tokens_map.json); SD 1.x with the end token.
        let pad = match std::fs::read_to_string(dir.join("special_tokens_map.json")) {
            Ok(t) => {
                let v: Value = serde_json::from_str(&t).map_err(|e| DiffusionError::Config {
                    path: dir.join("special_tokens_map.json"),
                    problem: e.to_string(),
                })?;
                let p = v.get("pad_token").and_then(|p| {
                    p.as_str().map(str::to_string).or_else(|| {
                        p.get("content")
                            .and_then(|c| c.as_str())
                            .map(str::to_string)
                    })
                });
                match p {
                    Some(p) => id(&p)?,
                    None => eos,
                }
            }
            Err(_) => eos,
        };
        Ok(ClipTokenizer {
            vocab,
            ranks,
            byte_char: bytes_to_unicode(),
            bos,
            eos,
            pad,
        })
    }

    fn words(text: &str) -> Vec<String> {
        let text = text
            .split_whitespace()
            .collect::<Vec<_>>()
            .join(" ")
            .to_lowercase();
        let chars: Vec<char> = text.chars().collect();
        let mut out = Vec::new();
        let mut i = 0;
        while i < chars.len() {
            let c = chars[i];
            if c.is_whitespace() {
                i += 1;
                continue;
            }
            let rest: String = chars[i..chars.len().min(i + 15)].iter().collect();
            if let Some(sp) = ["<|startoftext|>", "<|endoftext|>"]
                .iter()
                .find(|s| rest.starts_with(*s))
            {
                out.push(sp.to_string());
                i += sp.chars().count();
                continue;
            }
            if c == '\'' {
                if let Some(k) = ["'s", "'t", "'re", "'ve", "'m", "'ll", "'d"]
                    .iter()
                    .find(|k| rest.starts_with(*k))
                {
                    out.push(k.to_string());
                    i += k.len();
                    continue;
                }
            }
            let start = i;
            if c.is_alphabetic() {
                while i < chars.len() && chars[i].is_alphabetic() {
                    i += 1;
                }
            } else if c.is_numeric() {
                i += 1;
            } else {
                while i < chars.len()
                    && !chars[i].is_whitespace()
                    && !chars[i].is_alphabetic()
                    && !chars[i].is_numeric()
                {
                    i += 1;
                }
            }
            out.push(chars[start..i].iter().collect());
        }
        out
    }

    fn bpe(&self, word: &str) -> Vec<String> {
        let mapped: Vec<char> = word.bytes().map(|b| self.byte_char[b as usize]).collect();
        let mut parts: Vec<String> = mapped.iter().map(|c| c.to_string()).collect();
        if let Some(last) = parts.last_mut() {
            last.push_str("</w>");
        }
        loop {
            let best = parts
                .windows(2)
                .enumerate()
                .filter_map(|(i, w)| {
                    self.ranks
                        .get(&(w[0].clone(), w[1].clone()))
                        .map(|r| (*r, i))
                })
                .min();
            let Some((_, i)) = best else { break };
            let merged = format!("{}{}", parts[i], parts[i + 1]);
            parts.splice(i..i + 2, [merged]);
        }
        parts
    }

    /// Token ids of `text`: start, the words' tokens, end, padded to `len` (truncated to keep
    /// the end token). Symbols outside the vocabulary are an error naming them.
    pub fn encode(&self, text: &str, len: usize) -> Result<Vec<u32>> {
        let mut ids = vec![self.bos];
        for w in Self::words(text) {
            if let Some(&id) = self.vocab.get(&w) {
                if w.starts_with("<|") {
                    ids.push(id);
                    continue;
                }
            }
            for t in self.bpe(&w) {
                let id = self.vocab.get(&t).copied().ok_or_else(|| {
                    DiffusionError::Input(format!("token {t:?} of {w:?} is not in the vocabulary"))
                })?;
                ids.push(id);
            }
        }
        ids.truncate(len.saturating_sub(1).max(1));
        ids.push(self.eos);
        ids.resize(len.max(ids.len()), self.pad);
        Ok(ids)
    }
}

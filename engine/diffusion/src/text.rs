//! Conditioning for cross-attention.
//!
//! Without text-encoder weights the U-Net is conditioned on learned token embeddings: a small
//! table of vectors trained with the model (the DreamBooth identifier of the scene). The null
//! conditioning for classifier-free guidance is the zero sequence of the same shape.

use std::path::Path;

use burn::module::{Module, Param};
use burn::nn::Initializer;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::{DiffusionError, Result};

/// Learned conditioning tokens `[tokens, dim]`.
#[derive(Module, Debug)]
pub struct LearnedTokens {
    /// The embeddings.
    pub tokens: Param<Tensor<2>>,
    /// The unconditional context for guidance and for conditioning dropout in training (CLIP's
    /// empty-prompt embedding when the tokens started from a prompt); zeros when None. Saved,
    /// never trained.
    pub null_tokens: Option<Param<Tensor<2>>>,
}

/// `text_encoder/config.json` of a learned-token conditioning.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnedTokensConfig {
    /// Always "LearnedTokens".
    #[serde(rename = "_class_name")]
    pub class_name: String,
    /// Number of tokens.
    pub tokens: usize,
    /// Width (the U-Net's cross_attention_dim).
    pub dim: usize,
    /// The file also holds `null_tokens` (the guidance baseline), else the baseline is zeros.
    #[serde(default)]
    pub null_tokens: bool,
}

/// File name of the learned tokens.
pub const TOKENS_FILE: &str = "learned_tokens.safetensors";

impl LearnedTokens {
    /// `n` tokens of width `dim`, N(0, 1) (the scale of the normalised text features the
    /// cross-attention projections expect).
    pub fn new(n: usize, dim: usize, device: &Device) -> LearnedTokens {
        LearnedTokens {
            tokens: Initializer::Normal {
                mean: 0.0,
                std: 1.0,
            }
            .init([n, dim], device),
            null_tokens: None,
        }
    }

    /// Tokens initialised from a text embedding `[n, dim]` (a CLIP prompt), with the empty
    /// prompt's embedding as the null context.
    pub fn from_embedding(prompt: Tensor<2>, empty: Tensor<2>) -> LearnedTokens {
        LearnedTokens {
            tokens: Param::from_tensor(prompt),
            null_tokens: Some(Param::from_tensor(empty).set_require_grad(false)),
        }
    }

    /// `[n, dim]`.
    pub fn dims(&self) -> [usize; 2] {
        let s = self.tokens.lazy_shape();
        [s[0], s[1]]
    }

    /// The context for a batch: `[batch, n, dim]`.
    pub fn forward(&self, batch: usize) -> Tensor<3> {
        let [n, d] = self.dims();
        self.tokens.val().unsqueeze::<3>().expand([batch, n, d])
    }

    /// The null context for guidance `[batch, n, dim]`: the empty prompt's embedding, or zeros.
    pub fn null(&self, batch: usize, device: &Device) -> Tensor<3> {
        let [n, d] = self.dims();
        match &self.null_tokens {
            Some(t) => t.val().detach().unsqueeze::<3>().expand([batch, n, d]),
            None => Tensor::zeros([batch, n, d], device),
        }
    }

    /// Writes `dir/config.json` and `dir/learned_tokens.safetensors`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        let [n, d] = self.dims();
        crate::weights::save_from(self, &dir.join(TOKENS_FILE))?;
        crate::config::write_json(
            &dir.join("config.json"),
            &LearnedTokensConfig {
                class_name: "LearnedTokens".into(),
                tokens: n,
                dim: d,
                null_tokens: self.null_tokens.is_some(),
            },
        )
    }

    /// Reads what [`LearnedTokens::save`] wrote.
    pub fn load(dir: &Path, device: &Device) -> Result<LearnedTokens> {
        let path = dir.join("config.json");
        let c: LearnedTokensConfig = crate::config::read_json(&path)?;
        if c.class_name != "LearnedTokens" || c.tokens == 0 || c.dim == 0 {
            return Err(DiffusionError::Config {
                path,
                problem: format!(
                    "expected a LearnedTokens config with tokens > 0 and dim > 0, got {:?} ({} x {})",
                    c.class_name, c.tokens, c.dim
                ),
            });
        }
        let mut t = LearnedTokens::new(c.tokens, c.dim, device);
        if c.null_tokens {
            t.null_tokens = Some(
                Initializer::Zeros
                    .init([c.tokens, c.dim], device)
                    .set_require_grad(false),
            );
        }
        crate::weights::load_into(&mut t, &dir.join(TOKENS_FILE), &[], &[])?;
        Ok(t)
    }
}

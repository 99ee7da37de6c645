//! LoRA settings: targets, rank, alpha, dropout (docs/method.md §9).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::candle::DepthAnythingConfig;

/// A linear layer (or part of `attn.qkv`) of every DINOv2 block that gets an adapter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LoraTarget {
    /// The query rows of `attn.qkv` (default, as the authors).
    Q,
    /// The key rows of `attn.qkv`.
    K,
    /// The value rows of `attn.qkv` (default, as the authors).
    V,
    /// `attn.proj`.
    Proj,
    /// `mlp.fc1`.
    Fc1,
    /// `mlp.fc2`.
    Fc2,
}

impl LoraTarget {
    /// Every target, in order.
    pub const ALL: [Self; 6] = [Self::Q, Self::K, Self::V, Self::Proj, Self::Fc1, Self::Fc2];

    /// The authors' default: q and v of `attn.qkv`.
    pub const DEFAULT: [Self; 2] = [Self::Q, Self::V];

    /// The target's key inside a block: `attn.qkv.q`, `attn.proj`, `mlp.fc1`, ….
    pub fn key(self) -> &'static str {
        match self {
            Self::Q => "attn.qkv.q",
            Self::K => "attn.qkv.k",
            Self::V => "attn.qkv.v",
            Self::Proj => "attn.proj",
            Self::Fc1 => "mlp.fc1",
            Self::Fc2 => "mlp.fc2",
        }
    }

    /// The official weight the adapter adds to (inside a block): `attn.qkv.weight`, ….
    pub fn weight_key(self) -> &'static str {
        match self {
            Self::Q | Self::K | Self::V => "attn.qkv.weight",
            Self::Proj => "attn.proj.weight",
            Self::Fc1 => "mlp.fc1.weight",
            Self::Fc2 => "mlp.fc2.weight",
        }
    }

    /// `(in, rows, first row)` of the adapted output slice for embedding width `d` and MLP width
    /// `hidden`.
    pub fn shape(self, d: usize, hidden: usize) -> (usize, usize, usize) {
        match self {
            Self::Q => (d, d, 0),
            Self::K => (d, d, d),
            Self::V => (d, d, 2 * d),
            Self::Proj => (d, d, 0),
            Self::Fc1 => (d, hidden, 0),
            Self::Fc2 => (hidden, d, 0),
        }
    }
}

impl fmt::Display for LoraTarget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Q => "q",
            Self::K => "k",
            Self::V => "v",
            Self::Proj => "proj",
            Self::Fc1 => "fc1",
            Self::Fc2 => "fc2",
        })
    }
}

impl FromStr for LoraTarget {
    type Err = String;

    /// `q`, `k`, `v`, `proj` (or `attn.proj`), `fc1`/`fc2` (or `mlp.fc1`/`mlp.fc2`).
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "q" => Ok(Self::Q),
            "k" => Ok(Self::K),
            "v" => Ok(Self::V),
            "proj" | "attn.proj" => Ok(Self::Proj),
            "fc1" | "mlp.fc1" => Ok(Self::Fc1),
            "fc2" | "mlp.fc2" => Ok(Self::Fc2),
            other => Err(format!(
                "unknown LoRA target {other:?} (expected q, k, v, proj, fc1 or fc2)"
            )),
        }
    }
}

/// The largest LoRA alpha per unit of rank (an update scale alpha / rank of 1000): far above the
/// 1–2 of practice, and below the scales at which the adapted network's f32 output no longer
/// survives its own reload (alpha 1e30 trained to a validation loss that the written adapter,
/// reloaded, did not reproduce).
pub const MAX_ALPHA_PER_RANK: f64 = 1000.0;

/// LoRA settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoraConfig {
    /// Rank r.
    pub rank: usize,
    /// Alpha; the update is scaled by α / r.
    pub alpha: f64,
    /// Adapted layers of every block.
    pub targets: Vec<LoraTarget>,
    /// Dropout probability on the adapter input (0 = none).
    pub dropout: f32,
    /// Seed of A's initialisation and of the dropout masks.
    pub seed: u64,
}

impl LoraConfig {
    /// Rank `rank`, alpha = rank, q and v, no dropout, seed 0.
    pub fn new(rank: usize) -> Self {
        Self {
            rank,
            alpha: rank as f64,
            targets: LoraTarget::DEFAULT.to_vec(),
            dropout: 0.0,
            seed: 0,
        }
    }

    /// Checks the settings against the network.
    ///
    /// # Errors
    /// A readable reason: rank 0 or larger than a layer's smaller side, alpha ≤ 0 or not finite,
    /// dropout outside [0, 1), no or repeated targets.
    pub fn validate(&self, config: &DepthAnythingConfig) -> Result<(), String> {
        if self.targets.is_empty() {
            return Err("no LoRA targets".into());
        }
        let mut seen = self.targets.clone();
        seen.sort_unstable();
        seen.dedup();
        if seen.len() != self.targets.len() {
            return Err("repeated LoRA target".into());
        }
        if self.rank == 0 {
            return Err("LoRA rank must be at least 1".into());
        }
        for t in &self.targets {
            let (i, o, _) = t.shape(config.embed_dim, config.mlp_hidden_dim);
            if self.rank > i.min(o) {
                return Err(format!(
                    "LoRA rank {} is larger than layer {} ({o}x{i})",
                    self.rank,
                    t.key()
                ));
            }
        }
        if !(self.alpha.is_finite() && self.alpha > 0.0) {
            return Err(format!("LoRA alpha {} must be positive", self.alpha));
        }
        if self.alpha > MAX_ALPHA_PER_RANK * self.rank as f64 {
            return Err(format!(
                "LoRA alpha {:e} is more than {MAX_ALPHA_PER_RANK} × the rank {}: the update \
                 scale alpha / rank would swamp the base weights (alpha is usually 1–2 × rank)",
                self.alpha, self.rank
            ));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(format!("LoRA dropout {} must be in [0, 1)", self.dropout));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Head;

    #[test]
    fn targets_parse_print_and_validate() {
        for t in LoraTarget::ALL {
            assert_eq!(t.to_string().parse::<LoraTarget>(), Ok(t));
        }
        assert_eq!("mlp.fc1".parse::<LoraTarget>(), Ok(LoraTarget::Fc1));
        assert!("qk".parse::<LoraTarget>().unwrap_err().contains("unknown"));
        let c = DepthAnythingConfig::vit_small(Head::Relative);
        assert!(LoraConfig::new(16).validate(&c).is_ok());
        assert!(LoraConfig::new(0).validate(&c).is_err());
        assert!(
            LoraConfig::new(385)
                .validate(&c)
                .unwrap_err()
                .contains("larger")
        );
        let mut l = LoraConfig::new(4);
        l.alpha = 0.0;
        assert!(l.validate(&c).is_err());
        l.alpha = 4.0;
        l.targets = vec![LoraTarget::Q, LoraTarget::Q];
        assert!(l.validate(&c).is_err());
    }
}

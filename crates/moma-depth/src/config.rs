//! Custom network sizes: the architecture of a Depth Anything V2 network that is not one of the
//! released ViT-S/B/L models, read from a JSON file.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::{Backbone, DepthError, Head, ModelSpec, Result};

/// The architecture of a custom-size Depth Anything V2 network (MLP hidden width 4 × `embed_dim`,
/// 14-pixel patches and a 37 × 37 stored position grid, as every DINOv2 of Depth Anything V2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct CustomArch {
    /// Token width of the ViT.
    pub embed_dim: usize,
    /// Number of transformer blocks.
    pub depth: usize,
    /// Attention heads per block (`embed_dim` must be a multiple).
    pub num_heads: usize,
    /// 0-based blocks whose normalised outputs feed the DPT head.
    pub intermediate_layers: [usize; 4],
    /// Channels of the DPT fusion path.
    pub features: usize,
    /// Channels of the four DPT projections.
    pub out_channels: [usize; 4],
}

impl CustomArch {
    /// Checks that the sizes describe a buildable network.
    ///
    /// # Errors
    /// A readable reason when they do not.
    pub fn validate(&self) -> std::result::Result<(), String> {
        if self.embed_dim == 0 || self.depth == 0 {
            return Err("embed_dim and depth must be positive".into());
        }
        if self.num_heads == 0 || !self.embed_dim.is_multiple_of(self.num_heads) {
            return Err(format!(
                "embed_dim {} is not a multiple of num_heads {}",
                self.embed_dim, self.num_heads
            ));
        }
        if let Some(l) = self.intermediate_layers.iter().find(|&&l| l >= self.depth) {
            return Err(format!(
                "intermediate layer {l} >= depth {} (layers are 0-based)",
                self.depth
            ));
        }
        if self.features < 2 || !self.features.is_multiple_of(2) {
            return Err(format!(
                "features {} must be an even number >= 2",
                self.features
            ));
        }
        if self.out_channels.contains(&0) {
            return Err("out_channels must be positive".into());
        }
        Ok(())
    }
}

/// Head names of a configuration file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HeadName {
    /// Relative head (inverse depth).
    Relative,
    /// Metric head (metres, up to `max_depth`).
    Metric,
}

/// A model configuration file (`--model PATH.json`), e.g. the tiny reference models:
/// `{"embed_dim":64,"depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,
/// "out_channels":[8,16,32,64],"head":"metric","max_depth":20}`. `max_depth` (metres) is required
/// for a metric head and ignored for a relative one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfigFile {
    /// Token width of the ViT.
    pub embed_dim: usize,
    /// Number of transformer blocks.
    pub depth: usize,
    /// Attention heads per block.
    pub num_heads: usize,
    /// 0-based blocks that feed the DPT head.
    pub intermediate_layers: [usize; 4],
    /// Channels of the DPT fusion path.
    pub features: usize,
    /// Channels of the four DPT projections.
    pub out_channels: [usize; 4],
    /// `relative` or `metric`.
    pub head: HeadName,
    /// Largest depth of a metric head, metres.
    #[serde(default)]
    pub max_depth: Option<f32>,
}

impl ModelConfigFile {
    /// Reads and checks a configuration file.
    ///
    /// # Errors
    /// [`DepthError::Config`] naming the file: unreadable, not this JSON shape, inconsistent sizes,
    /// a metric head without a positive `max_depth`.
    pub fn read(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let err = |reason: String| DepthError::Config {
            path: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        Self::from_json(&text).map_err(err)
    }

    /// Parses and checks the JSON of a configuration file (what [`Self::read`] reads).
    ///
    /// # Errors
    /// Why it is not one: not this JSON shape, inconsistent sizes, a metric head without a
    /// positive `max_depth`.
    pub fn from_json(text: &str) -> std::result::Result<Self, String> {
        let file: Self = serde_json::from_str(text).map_err(|e| e.to_string())?;
        file.arch().validate()?;
        file.head_checked()?;
        Ok(file)
    }

    /// The architecture.
    pub fn arch(&self) -> CustomArch {
        CustomArch {
            embed_dim: self.embed_dim,
            depth: self.depth,
            num_heads: self.num_heads,
            intermediate_layers: self.intermediate_layers,
            features: self.features,
            out_channels: self.out_channels,
        }
    }

    fn head_checked(&self) -> std::result::Result<Head, String> {
        match (self.head, self.max_depth) {
            (HeadName::Relative, _) => Ok(Head::Relative),
            (HeadName::Metric, Some(m)) if m.is_finite() && m > 0.0 => {
                Ok(Head::Metric { max_depth_m: m })
            }
            (HeadName::Metric, Some(m)) => {
                Err(format!("max_depth {m} must be a positive number of metres"))
            }
            (HeadName::Metric, None) => Err("a metric head needs max_depth (metres)".into()),
        }
    }

    /// The head the file fixes (a file that passed [`Self::read`] always has a valid one; an
    /// invalid metric `max_depth` gives a relative head here, never a panic).
    pub fn head(&self) -> Head {
        self.head_checked().unwrap_or(Head::Relative)
    }

    /// The model this file describes, with network input lower bound `input_size` pixels.
    pub fn spec(&self, input_size: usize) -> ModelSpec {
        ModelSpec {
            backbone: Backbone::Custom(self.arch()),
            head: self.head(),
            input_size,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(text: &str) -> tempfile::NamedTempFile {
        let f = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(f.path(), text).unwrap();
        f
    }

    #[test]
    fn reads_the_tiny_configuration_of_the_issue() {
        let f = write(
            r#"{"embed_dim":64,"depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64],"head":"metric","max_depth":20}"#,
        );
        let c = ModelConfigFile::read(f.path()).unwrap();
        assert_eq!(c.head(), Head::Metric { max_depth_m: 20.0 });
        let spec = c.spec(518);
        let Backbone::Custom(arch) = spec.backbone else {
            panic!("not custom")
        };
        assert_eq!(arch.embed_dim, 64);
        assert_eq!(arch.out_channels, [8, 16, 32, 64]);
        let rel = write(
            r#"{"embed_dim":64,"depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64],"head":"relative","max_depth":20}"#,
        );
        assert_eq!(
            ModelConfigFile::read(rel.path()).unwrap().head(),
            Head::Relative
        );
    }

    #[test]
    fn bad_configurations_name_the_file_and_the_problem() {
        let base = r#""depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64]"#;
        for (text, needle) in [
            (format!(r#"{{"embed_dim":63,{base},"head":"relative"}}"#), "multiple"),
            (format!(r#"{{"embed_dim":64,{base},"head":"metric"}}"#), "max_depth"),
            (
                format!(r#"{{"embed_dim":64,{base},"head":"metric","max_depth":-1}}"#),
                "positive",
            ),
            (format!(r#"{{"embed_dim":64,{base},"head":"sideways"}}"#), "variant"),
            (format!(r#"{{"embed_dim":64,{base},"head":"relative","x":1}}"#), "unknown field"),
            (
                r#"{"embed_dim":64,"depth":2,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64],"head":"relative"}"#.into(),
                "intermediate layer",
            ),
        ] {
            let f = write(&text);
            let e = ModelConfigFile::read(f.path()).unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
            assert!(e.contains(&f.path().display().to_string()), "{e}");
        }
        assert!(ModelConfigFile::read("/nonexistent/tiny.json").is_err());
    }
}

//! The public Depth Anything V2 checkpoints by name, and (feature `hub`) fetching them.
//!
//! The official releases are PyTorch `.pth` state dicts on the Hugging Face Hub; the candle
//! backend loads them as they are. [`CHECKPOINTS`] is always compiled in, so a build without
//! network access can still tell the user which file to download and from where
//! ([`Checkpoint::url`]). With the `hub` feature, [`fetch`] looks in the Hugging Face cache first
//! (the layout Python's `huggingface_hub` uses: `$HF_HUB_CACHE`, else `$HF_HOME/hub`, else
//! `~/.cache/huggingface/hub`, so files already downloaded by Python are found offline), then
//! downloads (`$HF_ENDPOINT` for a mirror; `HF_HUB_OFFLINE=1` forbids downloading).
//!
//! Licences differ: the ViT-S checkpoints are Apache-2.0; ViT-B and ViT-L are CC-BY-NC-4.0
//! (non-commercial). [`Checkpoint::licence`] says which.

use std::path::{Path, PathBuf};

use crate::preprocess::DEFAULT_INPUT_SIZE;
use crate::{Backbone, DepthError, Head, ModelSpec, Result};

/// One public checkpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Checkpoint {
    /// The short name users type (`vits`, `metric-hypersim-vitl`, ...).
    pub name: &'static str,
    /// Hugging Face model repository.
    pub repo: &'static str,
    /// File in the repository.
    pub file: &'static str,
    /// Backbone.
    pub backbone: Backbone,
    /// Head (metric heads with their training `max_depth`: 20 m Hypersim, 80 m Virtual KITTI).
    pub head: Head,
    /// SPDX licence of the weights.
    pub licence: &'static str,
}

const HYPERSIM: Head = Head::Metric { max_depth_m: 20.0 };
const VKITTI: Head = Head::Metric { max_depth_m: 80.0 };
const APACHE: &str = "Apache-2.0";
const NON_COMMERCIAL: &str = "CC-BY-NC-4.0";

macro_rules! checkpoint {
    ($name:literal, $repo:literal, $file:literal, $backbone:ident, $head:expr, $licence:expr) => {
        Checkpoint {
            name: $name,
            repo: concat!("depth-anything/", $repo),
            file: $file,
            backbone: Backbone::$backbone,
            head: $head,
            licence: $licence,
        }
    };
}

/// The official Depth Anything V2 checkpoints (relative, and metric indoor / outdoor).
pub const CHECKPOINTS: &[Checkpoint] = &[
    checkpoint!(
        "vits",
        "Depth-Anything-V2-Small",
        "depth_anything_v2_vits.pth",
        Vits,
        Head::Relative,
        APACHE
    ),
    checkpoint!(
        "vitb",
        "Depth-Anything-V2-Base",
        "depth_anything_v2_vitb.pth",
        Vitb,
        Head::Relative,
        NON_COMMERCIAL
    ),
    checkpoint!(
        "vitl",
        "Depth-Anything-V2-Large",
        "depth_anything_v2_vitl.pth",
        Vitl,
        Head::Relative,
        NON_COMMERCIAL
    ),
    checkpoint!(
        "metric-hypersim-vits",
        "Depth-Anything-V2-Metric-Hypersim-Small",
        "depth_anything_v2_metric_hypersim_vits.pth",
        Vits,
        HYPERSIM,
        APACHE
    ),
    checkpoint!(
        "metric-hypersim-vitb",
        "Depth-Anything-V2-Metric-Hypersim-Base",
        "depth_anything_v2_metric_hypersim_vitb.pth",
        Vitb,
        HYPERSIM,
        NON_COMMERCIAL
    ),
    checkpoint!(
        "metric-hypersim-vitl",
        "Depth-Anything-V2-Metric-Hypersim-Large",
        "depth_anything_v2_metric_hypersim_vitl.pth",
        Vitl,
        HYPERSIM,
        NON_COMMERCIAL
    ),
    checkpoint!(
        "metric-vkitti-vits",
        "Depth-Anything-V2-Metric-VKITTI-Small",
        "depth_anything_v2_metric_vkitti_vits.pth",
        Vits,
        VKITTI,
        APACHE
    ),
    checkpoint!(
        "metric-vkitti-vitb",
        "Depth-Anything-V2-Metric-VKITTI-Base",
        "depth_anything_v2_metric_vkitti_vitb.pth",
        Vitb,
        VKITTI,
        NON_COMMERCIAL
    ),
    checkpoint!(
        "metric-vkitti-vitl",
        "Depth-Anything-V2-Metric-VKITTI-Large",
        "depth_anything_v2_metric_vkitti_vitl.pth",
        Vitl,
        VKITTI,
        NON_COMMERCIAL
    ),
];

impl Checkpoint {
    /// The network this checkpoint is, at the default input size (518).
    pub fn spec(&self) -> ModelSpec {
        ModelSpec {
            backbone: self.backbone,
            head: self.head,
            input_size: DEFAULT_INPUT_SIZE,
        }
    }

    /// Direct download address (`https://huggingface.co/REPO/resolve/main/FILE`).
    pub fn url(&self) -> String {
        format!(
            "https://huggingface.co/{}/resolve/main/{}",
            self.repo, self.file
        )
    }
}

/// The checkpoint called `name` (case-insensitive).
///
/// # Errors
/// [`DepthError::Unavailable`] naming the known checkpoints.
pub fn find(name: &str) -> Result<&'static Checkpoint> {
    CHECKPOINTS
        .iter()
        .find(|c| c.name.eq_ignore_ascii_case(name.trim()))
        .ok_or_else(|| {
            let names: Vec<&str> = CHECKPOINTS.iter().map(|c| c.name).collect();
            DepthError::Unavailable(format!(
                "unknown checkpoint {name:?}; known: {}",
                names.join(", ")
            ))
        })
}

/// The Hugging Face cache directory, as Python's `huggingface_hub` resolves it: `$HF_HUB_CACHE`,
/// else `$HF_HOME/hub`, else `~/.cache/huggingface/hub`.
pub fn cache_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("HF_HUB_CACHE").filter(|d| !d.is_empty()) {
        return PathBuf::from(dir);
    }
    if let Some(home) = std::env::var_os("HF_HOME").filter(|d| !d.is_empty()) {
        return PathBuf::from(home).join("hub");
    }
    let home = std::env::var_os("HOME")
        .map(PathBuf::from)
        .unwrap_or_default();
    home.join(".cache").join("huggingface").join("hub")
}

/// Local path of `checkpoint`: from the Hugging Face cache ([`cache_dir`]), else downloaded into it
/// (feature `hub`). See [`fetch_in`].
///
/// # Errors
/// As [`fetch_in`].
pub fn fetch(checkpoint: &Checkpoint) -> Result<PathBuf> {
    fetch_in(&cache_dir(), checkpoint)
}

/// Local path of `checkpoint` in the Hugging Face cache `cache`
/// (`cache/models--OWNER--NAME/snapshots/<refs/main>/FILE`); when absent, with the `hub` feature,
/// downloaded into it (`$HF_ENDPOINT` for a mirror) unless `HF_HUB_OFFLINE` is set.
///
/// # Errors
/// [`DepthError::Unavailable`] when the file is not cached and cannot be downloaded (no `hub`
/// feature, `HF_HUB_OFFLINE`, or a failed download); the message gives the download address.
pub fn fetch_in(cache: &Path, checkpoint: &Checkpoint) -> Result<PathBuf> {
    if let Some(path) = cached_path(cache, checkpoint) {
        return Ok(path);
    }
    let not_cached = |why: &str| {
        DepthError::Unavailable(format!(
            "{} is not in the Hugging Face cache {} and {why}; download {} and pass it as --weights",
            checkpoint.file,
            cache.display(),
            checkpoint.url()
        ))
    };
    if std::env::var("HF_HUB_OFFLINE").is_ok_and(|v| !matches!(v.as_str(), "" | "0")) {
        return Err(not_cached("HF_HUB_OFFLINE is set"));
    }
    #[cfg(feature = "hub")]
    return download(cache, checkpoint);
    #[cfg(not(feature = "hub"))]
    Err(not_cached(
        "this build cannot download (rebuild with `--features hub`)",
    ))
}

/// `cache/models--OWNER--NAME/snapshots/<refs/main>/FILE`, if it exists.
fn cached_path(cache: &Path, checkpoint: &Checkpoint) -> Option<PathBuf> {
    let repo_dir = cache.join(format!("models--{}", checkpoint.repo.replace('/', "--")));
    let commit = std::fs::read_to_string(repo_dir.join("refs").join("main")).ok()?;
    let path = repo_dir
        .join("snapshots")
        .join(commit.trim())
        .join(checkpoint.file);
    path.is_file().then_some(path)
}

#[cfg(feature = "hub")]
fn download(cache: &Path, checkpoint: &Checkpoint) -> Result<PathBuf> {
    let fail = |e: hf_hub::api::sync::ApiError| {
        DepthError::Unavailable(format!(
            "downloading {}: {e} (or download it yourself and pass it as --weights)",
            checkpoint.url()
        ))
    };
    let mut builder =
        hf_hub::api::sync::ApiBuilder::from_cache(hf_hub::Cache::new(cache.to_path_buf()))
            .with_progress(true);
    if let Ok(endpoint) = std::env::var("HF_ENDPOINT") {
        builder = builder.with_endpoint(endpoint);
    }
    builder
        .build()
        .map_err(fail)?
        .model(checkpoint.repo.to_string())
        .download(checkpoint.file)
        .map_err(fail)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_specs_match_the_files() {
        let mut names: Vec<&str> = CHECKPOINTS.iter().map(|c| c.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), CHECKPOINTS.len());
        for c in CHECKPOINTS {
            let tag = match c.backbone {
                Backbone::Vits => "vits",
                Backbone::Vitb => "vitb",
                Backbone::Vitl => "vitl",
                Backbone::Custom(_) => panic!("{}: hub checkpoints are released sizes", c.name),
            };
            assert!(c.file.ends_with(&format!("_{tag}.pth")), "{}", c.file);
            assert_eq!(c.spec().input_size, 518);
            match c.head {
                Head::Relative => assert!(!c.file.contains("metric")),
                Head::Metric { max_depth_m } => {
                    let want = if c.file.contains("hypersim") {
                        20.0
                    } else {
                        80.0
                    };
                    assert_eq!(max_depth_m, want, "{}", c.name);
                }
            }
            // Only the small models are Apache-2.0.
            assert_eq!(
                c.licence == APACHE,
                c.backbone == Backbone::Vits,
                "{}",
                c.name
            );
        }
        assert_eq!(
            find("VITS").unwrap().url(),
            "https://huggingface.co/depth-anything/Depth-Anything-V2-Small/resolve/main/depth_anything_v2_vits.pth"
        );
        let err = find("vit-huge").unwrap_err().to_string();
        assert!(err.contains("metric-vkitti-vitl"), "{err}");
    }

    #[test]
    fn cached_checkpoints_are_found_offline() {
        // The layout huggingface_hub writes: refs/main holds the commit, snapshots/COMMIT/FILE.
        let cache = tempfile::tempdir().unwrap();
        let c = find("metric-hypersim-vits").unwrap();
        let repo_dir = cache
            .path()
            .join("models--depth-anything--Depth-Anything-V2-Metric-Hypersim-Small");
        let snapshot = repo_dir.join("snapshots").join("0123abcd");
        std::fs::create_dir_all(&snapshot).unwrap();
        std::fs::create_dir_all(repo_dir.join("refs")).unwrap();
        std::fs::write(repo_dir.join("refs").join("main"), "0123abcd\n").unwrap();
        // Not there yet: without the `hub` feature the error gives the address.
        if !cfg!(feature = "hub") {
            let err = fetch_in(cache.path(), c).unwrap_err().to_string();
            assert!(err.contains(&c.url()), "{err}");
        }
        std::fs::write(snapshot.join(c.file), b"weights").unwrap();
        assert_eq!(fetch_in(cache.path(), c).unwrap(), snapshot.join(c.file));
    }
}

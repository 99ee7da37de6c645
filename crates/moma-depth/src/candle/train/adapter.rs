//! LoRA adapter files: safetensors with `blocks.{i}.{target}.lora_A|lora_B` (f32), every other
//! trained tensor under its official name (`depth_head.…` with `--train-head`), and metadata
//! (format, rank, alpha, targets, the architecture, the head, a fingerprint of the base weights,
//! training settings); merging an adapter into base weights at load time (no per-frame cost).
//!
//! Format versions: `moma-lora-v1` held the LoRA matrices only (a trained head stayed in the
//! optimiser state and was lost at inference); `moma-lora-v2` adds the trained non-LoRA tensors
//! and the head (`head`, `max_depth_m` metadata). Both load; v1 files simply have no trained
//! base tensors.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use safetensors::tensor::{Dtype, View};

use super::lora::{LoraConfig, LoraTarget};
use crate::candle::DepthAnythingConfig;
use crate::{DepthError, Result};

/// Value of the `format` metadata key of the adapters this version writes.
pub const ADAPTER_FORMAT: &str = "moma-lora-v2";

/// The first format (LoRA matrices only), still read.
pub const ADAPTER_FORMAT_V1: &str = "moma-lora-v1";

/// What the adapter's trained base tensors were trained under: the head and, for a metric head,
/// its maximum depth (the sigmoid's scale), metres.
fn head_label(head: crate::Head) -> (String, Option<String>) {
    match head {
        crate::Head::Relative => ("relative".into(), None),
        crate::Head::Metric { max_depth_m } => ("metric".into(), Some(max_depth_m.to_string())),
    }
}

/// A LoRA adapter: settings, what it was made for, and its matrices (f32, CPU).
#[derive(Debug, Clone)]
pub struct Adapter {
    /// Rank, alpha, targets (dropout and seed as trained).
    pub lora: LoraConfig,
    /// `embed_dim`, `depth`, `mlp_hidden_dim` of the network it was trained on.
    pub arch: (usize, usize, usize),
    /// [`fingerprint`] of the base weights.
    pub base_fingerprint: String,
    /// Training settings (free-form JSON, recorded for provenance).
    pub settings: serde_json::Value,
    /// `blocks.{i}.{target}.lora_A` `(r, in)` and `.lora_B` `(rows, r)`.
    pub tensors: BTreeMap<String, Tensor>,
    /// Trained non-LoRA tensors under their official names (`depth_head.…`), which replace the
    /// base weights' tensors at merge time (before the LoRA updates are added). Empty for
    /// adapters trained without `--train-head` and for `moma-lora-v1` files.
    pub base: BTreeMap<String, Tensor>,
    /// The head the adapter was trained with (`None` for `moma-lora-v1` files, which did not
    /// record it).
    pub head: Option<crate::Head>,
}

pub(crate) fn aerr(path: &Path, reason: impl Into<String>) -> DepthError {
    DepthError::Weights {
        path: path.display().to_string(),
        reason: reason.into(),
    }
}

pub(crate) fn backend(e: candle_core::Error) -> DepthError {
    DepthError::Backend(e.to_string())
}

/// A 64-bit FNV-1a fingerprint (hex) of every base tensor of `config` in `vb`: names, shapes and
/// the values in `f32`.
///
/// # Errors
/// Missing tensors.
pub fn fingerprint(vb: &VarBuilder, config: &DepthAnythingConfig) -> Result<String> {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    for (name, shape, required) in config.expected_tensors() {
        if !required {
            continue;
        }
        let t = vb
            .get(shape.clone(), &name)
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(backend)?;
        eat(name.as_bytes());
        for s in &shape {
            eat(&(*s as u64).to_le_bytes());
        }
        for v in t {
            eat(&v.to_le_bytes());
        }
    }
    Ok(format!("{h:016x}"))
}

/// Raw little-endian tensor bytes for safetensors serialisation (f32 unless `dtype` says f64).
pub(crate) struct F32View {
    pub(crate) shape: Vec<usize>,
    pub(crate) bytes: Vec<u8>,
    pub(crate) f64: bool,
}

impl F32View {
    /// A view of `t` in its own dtype when f64, else in f32 (bit-exact for f32 and f64).
    pub(crate) fn of(t: &Tensor) -> candle_core::Result<Self> {
        let t = t.detach().to_device(&Device::Cpu)?;
        let shape = t.dims().to_vec();
        let flat = t.flatten_all()?;
        Ok(if t.dtype() == DType::F64 {
            let v: Vec<f64> = flat.to_vec1()?;
            Self {
                shape,
                bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                f64: true,
            }
        } else {
            let v: Vec<f32> = flat.to_dtype(DType::F32)?.to_vec1()?;
            Self {
                shape,
                bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                f64: false,
            }
        })
    }
}

impl View for &F32View {
    fn dtype(&self) -> Dtype {
        if self.f64 { Dtype::F64 } else { Dtype::F32 }
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.bytes)
    }
    fn data_len(&self) -> usize {
        self.bytes.len()
    }
}

impl Adapter {
    /// Writes the adapter atomically (a temporary file in the same folder, then a rename).
    ///
    /// # Errors
    /// I/O errors naming the file; a tensor holding NaN or ±inf (a diverged run), which no
    /// reader takes: an adapter already at `path` is kept rather than replaced by it.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut views = BTreeMap::new();
        for (k, t) in self.tensors.iter().chain(&self.base) {
            let v: Vec<f32> = t
                .to_dtype(DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1())
                .map_err(backend)?;
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                return Err(aerr(
                    path,
                    format!("not written: tensor {k} holds {x} (the training diverged)"),
                ));
            }
            views.insert(
                k.clone(),
                F32View {
                    shape: t.dims().to_vec(),
                    bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                    f64: false,
                },
            );
        }
        let mut meta = HashMap::new();
        meta.insert("format".to_string(), ADAPTER_FORMAT.to_string());
        meta.insert("rank".into(), self.lora.rank.to_string());
        meta.insert("alpha".into(), self.lora.alpha.to_string());
        meta.insert(
            "targets".into(),
            self.lora
                .targets
                .iter()
                .map(|t| t.to_string())
                .collect::<Vec<_>>()
                .join(","),
        );
        meta.insert("dropout".into(), self.lora.dropout.to_string());
        meta.insert("seed".into(), self.lora.seed.to_string());
        let (d, depth, hidden) = self.arch;
        meta.insert("embed_dim".into(), d.to_string());
        meta.insert("depth".into(), depth.to_string());
        meta.insert("mlp_hidden_dim".into(), hidden.to_string());
        meta.insert("base_fingerprint".into(), self.base_fingerprint.clone());
        meta.insert("settings".into(), self.settings.to_string());
        if let Some(head) = self.head {
            let (kind, max_depth) = head_label(head);
            meta.insert("head".into(), kind);
            if let Some(m) = max_depth {
                meta.insert("max_depth_m".into(), m);
            }
        }
        meta.insert(
            "trained_base_tensors".into(),
            self.base.keys().cloned().collect::<Vec<_>>().join(","),
        );
        let bytes = safetensors::tensor::serialize(&views, Some(meta))
            .map_err(|e| aerr(path, e.to_string()))?;
        write_atomic(path, &bytes)
    }

    /// Reads an adapter file and checks it is complete and consistent.
    ///
    /// # Errors
    /// [`DepthError::Weights`] naming the file: unreadable, not safetensors, not a moma adapter,
    /// missing or mis-shaped matrices.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| aerr(path, e.to_string()))?;
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes)
            .map_err(|e| aerr(path, format!("not a safetensors file: {e}")))?;
        let meta = header
            .metadata()
            .clone()
            .ok_or_else(|| aerr(path, "no metadata: not a moma LoRA adapter"))?;
        let get = |k: &str| -> Result<&String> {
            meta.get(k)
                .ok_or_else(|| aerr(path, format!("metadata lacks `{k}`")))
        };
        let format = get("format")?;
        if format != ADAPTER_FORMAT && format != ADAPTER_FORMAT_V1 {
            return Err(aerr(
                path,
                format!(
                    "format {format:?}, expected {ADAPTER_FORMAT:?} (or the older {ADAPTER_FORMAT_V1:?})"
                ),
            ));
        }
        let num = |k: &str| -> Result<usize> {
            get(k)?
                .parse()
                .map_err(|_| aerr(path, format!("bad `{k}` in metadata")))
        };
        let lora = LoraConfig {
            rank: num("rank")?,
            alpha: get("alpha")?
                .parse()
                .map_err(|_| aerr(path, "bad `alpha` in metadata"))?,
            targets: get("targets")?
                .split(',')
                .map(|s| s.parse::<LoraTarget>())
                .collect::<std::result::Result<Vec<_>, String>>()
                .map_err(|e| aerr(path, e))?,
            dropout: get("dropout")?.parse().unwrap_or(0.0),
            seed: get("seed")?.parse().unwrap_or(0),
        };
        let arch = (num("embed_dim")?, num("depth")?, num("mlp_hidden_dim")?);
        let settings = serde_json::from_str(get("settings")?).unwrap_or(serde_json::Value::Null);
        let head = match meta.get("head").map(String::as_str) {
            None => None,
            Some("relative") => Some(crate::Head::Relative),
            Some("metric") => {
                let max_depth_m: f32 = get("max_depth_m")?
                    .parse()
                    .map_err(|_| aerr(path, "bad `max_depth_m` in metadata"))?;
                if !(max_depth_m.is_finite() && max_depth_m > 0.0) {
                    return Err(aerr(
                        path,
                        format!("max_depth_m {max_depth_m} out of range"),
                    ));
                }
                Some(crate::Head::Metric { max_depth_m })
            }
            Some(other) => {
                return Err(aerr(
                    path,
                    format!("head {other:?} in metadata (expected relative or metric)"),
                ));
            }
        };
        let mut tensors = BTreeMap::new();
        let mut base = BTreeMap::new();
        for (k, t) in candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)
            .map_err(|e| aerr(path, e.to_string()))?
        {
            check_finite(&k, &t).map_err(|e| aerr(path, e))?;
            if k.starts_with("blocks.") {
                tensors.insert(k, t);
            } else if format == ADAPTER_FORMAT_V1 {
                return Err(aerr(
                    path,
                    format!("unexpected tensor {k} in a {ADAPTER_FORMAT_V1} adapter"),
                ));
            } else {
                base.insert(k, t);
            }
        }
        if !base.is_empty() && head.is_none() {
            return Err(aerr(
                path,
                "trained base tensors but no `head` in metadata: cannot check the head they belong to",
            ));
        }
        let adapter = Self {
            lora,
            arch,
            base_fingerprint: get("base_fingerprint")?.clone(),
            settings,
            tensors,
            base,
            head,
        };
        adapter.check_shapes().map_err(|e| aerr(path, e))?;
        Ok(adapter)
    }

    /// Every expected matrix present with its shape, nothing else.
    fn check_shapes(&self) -> std::result::Result<(), String> {
        let (d, depth, hidden) = self.arch;
        let r = self.lora.rank;
        if r == 0
            || !(self.lora.alpha.is_finite()
                && self.lora.alpha > 0.0
                && self.lora.alpha <= super::lora::MAX_ALPHA_PER_RANK * r as f64)
        {
            return Err(format!("rank {r} / alpha {} out of range", self.lora.alpha));
        }
        let mut want = BTreeMap::new();
        for i in 0..depth {
            for t in &self.lora.targets {
                let (in_dim, rows, _) = t.shape(d, hidden);
                want.insert(format!("blocks.{i}.{}.lora_A", t.key()), vec![r, in_dim]);
                want.insert(format!("blocks.{i}.{}.lora_B", t.key()), vec![rows, r]);
            }
        }
        for (k, shape) in &want {
            match self.tensors.get(k) {
                None => return Err(format!("missing tensor {k}")),
                Some(t) if t.dims() != shape.as_slice() => {
                    return Err(format!("{k}: shape {:?}, expected {shape:?}", t.dims()));
                }
                Some(_) => {}
            }
        }
        if let Some(k) = self.tensors.keys().find(|k| !want.contains_key(*k)) {
            return Err(format!("unexpected tensor {k}"));
        }
        Ok(())
    }

    /// Checks that this adapter was made for `config` and base weights with `fingerprint`.
    ///
    /// # Errors
    /// A readable reason.
    pub fn check_base(
        &self,
        config: &DepthAnythingConfig,
        fingerprint: &str,
    ) -> std::result::Result<(), String> {
        let want = (config.embed_dim, config.depth, config.mlp_hidden_dim);
        if self.arch != want {
            return Err(format!(
                "adapter is for a network with (embed_dim, depth, mlp) {:?}, the model is {want:?}",
                self.arch
            ));
        }
        if self.base_fingerprint != fingerprint {
            return Err(format!(
                "adapter was trained on other base weights (fingerprint {}, these weights {fingerprint})",
                self.base_fingerprint
            ));
        }
        if let Some(head) = self.head
            && head != config.head
        {
            let show = |h: crate::Head| match h {
                crate::Head::Relative => "a relative head".to_string(),
                crate::Head::Metric { max_depth_m } => {
                    format!("a metric head (max depth {max_depth_m} m)")
                }
            };
            return Err(format!(
                "adapter was trained with {}, the model has {}",
                show(head),
                show(config.head)
            ));
        }
        let expected: BTreeMap<String, Vec<usize>> = config
            .expected_tensors()
            .into_iter()
            .map(|(n, s, _)| (n, s))
            .collect();
        for (name, t) in &self.base {
            match expected.get(name) {
                None => {
                    return Err(format!(
                        "trained tensor {name} is not a tensor of this model"
                    ));
                }
                Some(shape) if t.dims() != shape.as_slice() => {
                    return Err(format!(
                        "trained tensor {name}: shape {:?}, the model's is {shape:?}",
                        t.dims()
                    ));
                }
                Some(_) => {}
            }
        }
        Ok(())
    }

    /// The merged weights `W + (α/r)·B·A` (on the adapted rows) of every adapted layer, and the
    /// trained base tensors, keyed by the official name (`pretrained.blocks.{i}.attn.qkv.weight`,
    /// `depth_head.…`), read from `vb`.
    ///
    /// # Errors
    /// Missing base tensors.
    pub fn merged_weights(
        &self,
        vb: &VarBuilder,
        config: &DepthAnythingConfig,
    ) -> Result<HashMap<String, Tensor>> {
        let d = config.embed_dim;
        let hidden = config.mlp_hidden_dim;
        let scale = self.lora.alpha / self.lora.rank as f64;
        // Trained base tensors replace the base weights first; LoRA updates add to them (a
        // fully trained layer that also has an adapter was trained as `W + s·B·A`).
        let mut out: HashMap<String, Tensor> = self
            .base
            .iter()
            .map(|(k, t)| Ok((k.clone(), t.to_dtype(DType::F32)?)))
            .collect::<candle_core::Result<_>>()
            .map_err(backend)?;
        for i in 0..config.depth {
            for t in &self.lora.targets {
                let (in_dim, rows, offset) = t.shape(d, hidden);
                let name = format!("pretrained.blocks.{i}.{}", t.weight_key());
                let out_dim = match t {
                    LoraTarget::Q | LoraTarget::K | LoraTarget::V => 3 * d,
                    LoraTarget::Fc1 => hidden,
                    _ => d,
                };
                let w = match out.get(&name) {
                    Some(w) => w.clone(),
                    None => vb
                        .get((out_dim, in_dim), &name)
                        .and_then(|w| w.to_dtype(DType::F32))
                        .map_err(backend)?,
                };
                let key = format!("blocks.{i}.{}", t.key());
                let a = &self.tensors[&format!("{key}.lora_A")];
                let b = &self.tensors[&format!("{key}.lora_B")];
                let delta = b
                    .matmul(a)
                    .and_then(|m| m * scale)
                    .and_then(|m| m.to_device(w.device()))
                    .and_then(|m| m.pad_with_zeros(0, offset, out_dim - offset - rows))
                    .and_then(|m| w + m)
                    .map_err(backend)?;
                out.insert(name, delta);
            }
        }
        Ok(out)
    }
}

/// Base weights with some tensors replaced (the merged LoRA layers).
struct Merged {
    base: VarBuilder<'static>,
    over: HashMap<String, Tensor>,
}

impl candle_nn::var_builder::SimpleBackend for Merged {
    fn get(
        &self,
        s: candle_core::Shape,
        name: &str,
        _h: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = match self.over.get(name) {
            Some(t) if t.shape() != &s => {
                candle_core::bail!("merged {name}: shape {:?}, expected {s:?}", t.dims())
            }
            Some(t) => t.clone(),
            None => self.base.get(s, name)?,
        };
        t.to_dtype(dtype)?.to_device(dev)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = match self.over.get(name) {
            Some(t) => t.clone(),
            None => self.base.get_unchecked(name)?,
        };
        t.to_dtype(dtype)?.to_device(dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.over.contains_key(name) || self.base.contains_tensor(name)
    }
}

/// `base` with `adapter` merged in (after checking it was made for these weights): a
/// [`VarBuilder`] to build the inference network from (no per-frame cost).
///
/// # Errors
/// [`DepthError::Weights`] naming `adapter_path` when the adapter belongs to another model size
/// or other base weights; missing base tensors.
pub fn merge_adapter(
    base: VarBuilder<'static>,
    config: &DepthAnythingConfig,
    adapter: &Adapter,
    adapter_path: &Path,
) -> Result<VarBuilder<'static>> {
    let fp = fingerprint(&base, config)?;
    adapter
        .check_base(config, &fp)
        .map_err(|e| aerr(adapter_path, e))?;
    let over = adapter.merged_weights(&base, config)?;
    let dtype = base.dtype();
    let device = base.device().clone();
    Ok(VarBuilder::from_backend(
        Box::new(Merged { base, over }),
        dtype,
        device,
    ))
}

/// Writes the base weights `weights` with the adapter `adapter_path` merged in, as a full
/// `.safetensors` checkpoint in `f32` with the official key names (atomically): any runtime loads
/// it without knowing about LoRA.
///
/// # Errors
/// Unreadable weights or adapter, an adapter for other weights, I/O errors naming `out`.
pub fn write_merged(
    weights: &Path,
    config: &DepthAnythingConfig,
    adapter_path: &Path,
    out: &Path,
) -> Result<()> {
    let adapter = Adapter::load(adapter_path)?;
    let base = crate::candle::open_checkpoint(weights, config, &Device::Cpu, DType::F32)?;
    let merged = merge_adapter(base, config, &adapter, adapter_path)?;
    let mut views = BTreeMap::new();
    for (name, shape, required) in config.expected_tensors() {
        if !required && !merged.contains_tensor(&name) {
            continue;
        }
        let v: Vec<f32> = merged
            .get(shape.clone(), &name)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1())
            .map_err(backend)?;
        views.insert(
            name,
            F32View {
                shape,
                bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                f64: false,
            },
        );
    }
    let mut meta = HashMap::new();
    meta.insert(
        "merged_lora".to_string(),
        adapter_path.display().to_string(),
    );
    let bytes =
        safetensors::tensor::serialize(&views, Some(meta)).map_err(|e| aerr(out, e.to_string()))?;
    write_atomic(out, &bytes)
}

/// `Err` naming `name` when `t` holds a NaN or an infinity (a diverged run's adapter must not
/// load as if it were a model).
fn check_finite(name: &str, t: &Tensor) -> std::result::Result<(), String> {
    let bad = t
        .to_dtype(DType::F64)
        .and_then(|t| t.flatten_all())
        .and_then(|t| t.to_vec1::<f64>())
        .map_err(|e| format!("{name}: {e}"))?
        .iter()
        .filter(|v| !v.is_finite())
        .count();
    if bad > 0 {
        return Err(format!(
            "tensor {name} holds {bad} non-finite value(s) (NaN or infinity): the run that wrote it diverged"
        ));
    }
    Ok(())
}

/// Writes `bytes` through [`moma_io::atomic_write`]: a temporary file in the same folder, then
/// a rename; the temporary file is removed on an error, and by a `moma` command ended by a
/// signal.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    moma_io::atomic_write(path, |w| {
        w.write_all(bytes).map_err(|source| moma_io::IoError::Io {
            path: path.to_path_buf(),
            action: "write",
            source,
        })
    })
    .map_err(|e| aerr(path, format!("cannot write: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Head;
    use crate::candle::train::{LoraConfig, LoraTarget, ParamSource, TrainNet};

    fn tiny(head: Head) -> DepthAnythingConfig {
        DepthAnythingConfig {
            pos_grid: 4,
            ..crate::candle::tiny_test_config(head)
        }
    }

    /// Base weights with distinct deterministic values (a sine of the element index and a
    /// per-tensor phase).
    fn base(config: &DepthAnythingConfig) -> VarBuilder<'static> {
        let mut ts = HashMap::new();
        for (k, (name, shape, required)) in config.expected_tensors().into_iter().enumerate() {
            if !required {
                continue;
            }
            let n: usize = shape.iter().product();
            let v: Vec<f32> = (0..n)
                .map(|i| 0.1 * ((i as f32) * 0.37 + k as f32).sin())
                .collect();
            ts.insert(name, Tensor::from_vec(v, shape, &Device::Cpu).unwrap());
        }
        VarBuilder::from_tensors(ts, DType::F32, &Device::Cpu)
    }

    /// A trained adapter: LoRA on q and fc2 with non-zero B, and the head trained (every head
    /// tensor moved by a known amount).
    fn trained(config: &DepthAnythingConfig) -> Adapter {
        let src = ParamSource::new(base(config), |n: &str| n.starts_with("depth_head."));
        let mut net = TrainNet::new(config, src).unwrap();
        let mut lora = LoraConfig::new(2);
        lora.targets = vec![LoraTarget::Q, LoraTarget::Fc2];
        net.add_lora(&lora).unwrap();
        for v in net.lora_vars().values().chain(net.base_vars().values()) {
            v.set(&(v.as_tensor() + 0.25).unwrap()).unwrap();
        }
        let fp = fingerprint(&base(config), config).unwrap();
        net.adapter(&fp, serde_json::json!({})).unwrap()
    }

    fn get(vb: &VarBuilder, config: &DepthAnythingConfig, name: &str) -> Vec<f32> {
        let shape = config
            .expected_tensors()
            .into_iter()
            .find(|(n, _, _)| n == name)
            .unwrap()
            .1;
        vb.get(shape, name)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    }

    #[test]
    fn a_trained_head_travels_in_the_adapter_and_is_merged() {
        let head = Head::Metric { max_depth_m: 20.0 };
        let config = tiny(head);
        let a = trained(&config);
        assert_eq!(a.base.len(), 64, "every head tensor of the DPT head");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.safetensors");
        a.save(&path).unwrap();
        let b = Adapter::load(&path).unwrap();
        assert_eq!(b.head, Some(head));
        assert_eq!(
            b.base.keys().collect::<Vec<_>>(),
            a.base.keys().collect::<Vec<_>>()
        );
        let merged = merge_adapter(base(&config), &config, &b, &path).unwrap();
        let original = base(&config);
        // Head tensors: base + 0.25 exactly as trained; frozen encoder tensors unchanged.
        for name in [
            "depth_head.scratch.output_conv2.2.weight",
            "depth_head.projects.0.bias",
        ] {
            let (m, o) = (get(&merged, &config, name), get(&original, &config, name));
            for (x, y) in m.iter().zip(&o) {
                assert!((x - (y + 0.25)).abs() < 1e-6, "{name}: {x} vs {}", y + 0.25);
            }
        }
        let name = "pretrained.blocks.0.norm1.weight";
        assert_eq!(get(&merged, &config, name), get(&original, &config, name));
        // The adapted qkv rows: W + (α/r)·B·A with A, B = (init + 0.25), computed here by hand
        // for one element of the q rows; the k rows untouched.
        let w = get(&merged, &config, "pretrained.blocks.1.attn.qkv.weight");
        let w0 = get(&original, &config, "pretrained.blocks.1.attn.qkv.weight");
        let av: Vec<f32> = b.tensors["blocks.1.attn.qkv.q.lora_A"]
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let bv: Vec<f32> = b.tensors["blocks.1.attn.qkv.q.lora_B"]
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let (d, r) = (32, 2);
        let (row, col) = (5, 7);
        let delta: f32 = (0..r).map(|k| bv[row * r + k] * av[k * d + col]).sum();
        assert!((w[row * d + col] - (w0[row * d + col] + delta)).abs() < 1e-6);
        assert_eq!(w[(d + row) * d + col], w0[(d + row) * d + col]);
    }

    #[test]
    fn wrong_adapters_are_refused_naming_file_and_tensor() {
        let metric = tiny(Head::Metric { max_depth_m: 20.0 });
        let a = trained(&metric);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.safetensors");
        a.save(&path).unwrap();
        let loaded = Adapter::load(&path).unwrap();
        let msg = |r: Result<VarBuilder<'static>>| match r {
            Ok(_) => panic!("accepted"),
            Err(e) => e.to_string(),
        };
        // A trained metric head on a relative head (same weights: the fingerprint matches).
        let relative = tiny(Head::Relative);
        let e = msg(merge_adapter(base(&relative), &relative, &loaded, &path));
        assert!(
            e.contains("a.safetensors") && e.contains("metric head"),
            "{e}"
        );
        // Another maximum depth is another head.
        let other = tiny(Head::Metric { max_depth_m: 80.0 });
        let e = msg(merge_adapter(base(&other), &other, &loaded, &path));
        assert!(e.contains("max depth 20"), "{e}");
        // Another model size.
        let bigger = DepthAnythingConfig {
            depth: 3,
            intermediate_layers: [0, 1, 2, 2],
            ..metric.clone()
        };
        let e = msg(merge_adapter(base(&bigger), &bigger, &loaded, &path));
        assert!(e.contains("embed_dim"), "{e}");
        // A trained tensor the model does not have (a hand-edited file).
        let mut odd = loaded.clone();
        odd.base.insert(
            "depth_head.scratch.extra.weight".into(),
            Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
        );
        odd.save(&path).unwrap();
        let odd = Adapter::load(&path).unwrap();
        let e = msg(merge_adapter(base(&metric), &metric, &odd, &path));
        assert!(e.contains("depth_head.scratch.extra.weight"), "{e}");
        // NaN in a head tensor and in a LoRA matrix: never written (a diverged run keeps the
        // adapter it saved before), and refused at load from a file made elsewhere, naming the
        // tensor.
        loaded.save(&path).unwrap();
        let good = std::fs::read(&path).unwrap();
        for key in ["depth_head.projects.1.weight", "blocks.0.mlp.fc2.lora_B"] {
            let mut bad = loaded.clone();
            let map = if key.starts_with("blocks.") {
                &mut bad.tensors
            } else {
                &mut bad.base
            };
            let t = &map[key];
            let mut v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            v[1] = f32::NAN;
            let nan = Tensor::from_vec(v, t.dims(), &Device::Cpu).unwrap();
            map.insert(key.into(), nan);
            let e = bad.save(&path).unwrap_err().to_string();
            assert!(
                e.contains("a.safetensors") && e.contains(key) && e.contains("diverged"),
                "{e}"
            );
            assert_eq!(
                std::fs::read(&path).unwrap(),
                good,
                "the saved adapter is kept"
            );
            // the same NaN written into the file's bytes (the tensor's second value)
            let (n, meta) = safetensors::SafeTensors::read_metadata(&good).unwrap();
            let start = 8 + n + meta.info(key).unwrap().data_offsets.0 + 4;
            let mut bytes = good.clone();
            bytes[start..start + 4].copy_from_slice(&f32::NAN.to_le_bytes());
            std::fs::write(&path, &bytes).unwrap();
            let e = Adapter::load(&path).unwrap_err().to_string();
            assert!(
                e.contains("a.safetensors") && e.contains(key) && e.contains("non-finite"),
                "{e}"
            );
            std::fs::write(&path, &good).unwrap();
        }
    }

    #[test]
    fn version_1_adapters_still_load() {
        let config = tiny(Head::Metric { max_depth_m: 20.0 });
        let a = trained(&config);
        // The v1 layout: LoRA matrices only, the metadata of the first format.
        let mut views = BTreeMap::new();
        for (k, t) in &a.tensors {
            views.insert(k.clone(), F32View::of(t).unwrap());
        }
        let mut meta = HashMap::new();
        for (k, v) in [
            ("format", "moma-lora-v1".to_string()),
            ("rank", "2".into()),
            ("alpha", "2".into()),
            ("targets", "q,fc2".into()),
            ("dropout", "0".into()),
            ("seed", "0".into()),
            ("embed_dim", "32".into()),
            ("depth", "2".into()),
            ("mlp_hidden_dim", "64".into()),
            ("base_fingerprint", a.base_fingerprint.clone()),
            ("settings", "{}".into()),
        ] {
            meta.insert(k.to_string(), v);
        }
        let bytes = safetensors::tensor::serialize(&views, Some(meta.clone())).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v1.safetensors");
        std::fs::write(&path, bytes).unwrap();
        let v1 = Adapter::load(&path).unwrap();
        assert!(v1.base.is_empty() && v1.head.is_none());
        let merged = merge_adapter(base(&config), &config, &v1, &path).unwrap();
        let name = "depth_head.projects.0.bias";
        assert_eq!(
            get(&merged, &config, name),
            get(&base(&config), &config, name)
        );
        // A head tensor in a v1 file is not a v1 file.
        views.insert(
            "depth_head.projects.0.bias".into(),
            F32View::of(&a.base["depth_head.projects.0.bias"]).unwrap(),
        );
        let bytes = safetensors::tensor::serialize(&views, Some(meta)).unwrap();
        std::fs::write(&path, bytes).unwrap();
        let e = Adapter::load(&path).unwrap_err().to_string();
        assert!(
            e.contains("unexpected tensor depth_head.projects.0.bias"),
            "{e}"
        );
    }
}

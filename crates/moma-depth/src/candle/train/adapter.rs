//! LoRA adapter files: safetensors with `blocks.{i}.{target}.lora_A|lora_B` (f32) and metadata
//! (format, rank, alpha, targets, the architecture, a fingerprint of the base weights, training
//! settings); merging an adapter into base weights at load time (no per-frame cost).

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use safetensors::tensor::{Dtype, View};

use super::lora::{LoraConfig, LoraTarget};
use crate::candle::DepthAnythingConfig;
use crate::{DepthError, Result};

/// Value of the `format` metadata key.
pub const ADAPTER_FORMAT: &str = "moma-lora-v1";

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
    /// I/O errors naming the file.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut views = BTreeMap::new();
        for (k, t) in &self.tensors {
            let v: Vec<f32> = t
                .to_dtype(DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1())
                .map_err(backend)?;
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
        if get("format")? != ADAPTER_FORMAT {
            return Err(aerr(
                path,
                format!("format {:?}, expected {ADAPTER_FORMAT:?}", get("format")?),
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
        let tensors: BTreeMap<String, Tensor> =
            candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)
                .map_err(|e| aerr(path, e.to_string()))?
                .into_iter()
                .collect();
        let adapter = Self {
            lora,
            arch,
            base_fingerprint: get("base_fingerprint")?.clone(),
            settings,
            tensors,
        };
        adapter.check_shapes().map_err(|e| aerr(path, e))?;
        Ok(adapter)
    }

    /// Every expected matrix present with its shape, nothing else.
    fn check_shapes(&self) -> std::result::Result<(), String> {
        let (d, depth, hidden) = self.arch;
        let r = self.lora.rank;
        if r == 0 || !(self.lora.alpha.is_finite() && self.lora.alpha > 0.0) {
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
        Ok(())
    }

    /// The merged weights `W + (α/r)·B·A` (on the adapted rows) of every adapted layer, keyed by
    /// the official name (`pretrained.blocks.{i}.attn.qkv.weight`, …), read from `vb`.
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
        let mut out: HashMap<String, Tensor> = HashMap::new();
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

/// Temporary file in the same folder, then a rename.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
    let dir = dir.unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "weights".into());
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    std::fs::write(&tmp, bytes)
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            aerr(path, format!("cannot write: {e}"))
        })
}

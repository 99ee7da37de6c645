//! ONNX Runtime backend (feature `onnx`): runs Depth Anything V2 ONNX exports through the
//! [`ort`] crate (pinned `=2.0.0-rc.15`, `load-dynamic`, ONNX Runtime API ≥ 1.17).
//!
//! The ONNX Runtime shared library is **loaded at run time**, never downloaded or linked at build
//! time. [`find_runtime_library`] looks, in this order, at
//!
//! 1. `$ORT_DYLIB_PATH` (a file path; if set, it must exist — no silent fall-back),
//! 2. `./libonnxruntime.so` (current directory),
//! 3. `libonnxruntime.so` / `libonnxruntime.so.1.*` next to the running executable,
//! 4. the system loader (`libonnxruntime.so`, then `libonnxruntime.so.1`: `LD_LIBRARY_PATH`,
//!    `/etc/ld.so.conf` directories, `/usr/lib`, …).
//!
//! The PyPI wheel `onnxruntime` carries the library (`onnxruntime/capi/libonnxruntime.so.1.x`);
//! the repository script `.ci/install-onnxruntime.sh` installs it and prints its path:
//! `export ORT_DYLIB_PATH="$(.ci/install-onnxruntime.sh)"`. A missing or unusable library gives
//! [`DepthError::Unavailable`] with these instructions, never a panic.
//!
//! ```no_run
//! use moma_depth::onnx::{OnnxDepthModel, OnnxOptions};
//! use moma_depth::{Backbone, DepthModel, Head, ModelSpec};
//! let spec = ModelSpec { backbone: Backbone::Vits, head: Head::Relative, input_size: 518 };
//! let mut model = OnnxDepthModel::load("depth_anything_v2_vits.onnx", spec, &OnnxOptions::default())?;
//! let rgb = image::open("frame.png").unwrap().to_rgb8();
//! let pred = model.predict(&rgb)?;
//! # Ok::<(), moma_depth::DepthError>(())
//! ```

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use ndarray::{Array2, Array3};
use ort::environment::Environment;
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorElementType, TensorRef, ValueType};

use crate::error::{DepthError, Result};
use crate::{DepthModel, ModelSpec};

/// Environment variable naming the ONNX Runtime shared library (the `ort` crate's convention).
pub const ORT_DYLIB_ENV: &str = "ORT_DYLIB_PATH";

/// File name of the ONNX Runtime shared library on this platform (`libonnxruntime.so` on Linux).
pub fn library_file_name() -> String {
    format!(
        "{}onnxruntime{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    )
}

const INSTALL_HINT: &str = "install ONNX Runtime >= 1.17 (e.g. `pip install onnxruntime`, whose wheel \
     carries onnxruntime/capi/libonnxruntime.so.1.*, or run `.ci/install-onnxruntime.sh` in the moma \
     repository) and set ORT_DYLIB_PATH to the library file: \
     `export ORT_DYLIB_PATH=\"$(.ci/install-onnxruntime.sh)\"`";

/// The places [`find_runtime_library`] tries, in order (documented in the module docs). Entries that
/// are bare file names (no directory) are handed to the system loader.
///
/// # Errors
/// `$ORT_DYLIB_PATH` is set but does not name an existing file.
pub fn library_candidates() -> Result<Vec<PathBuf>> {
    if let Some(p) = std::env::var_os(ORT_DYLIB_ENV).filter(|p| !p.is_empty()) {
        let p = PathBuf::from(p);
        if !p.is_file() {
            return Err(DepthError::Unavailable(format!(
                "ONNX Runtime library not found: {ORT_DYLIB_ENV}={} is not a file; {INSTALL_HINT}",
                p.display()
            )));
        }
        return Ok(vec![p]);
    }
    let name = library_file_name();
    let mut out = Vec::new();
    let cwd_lib = PathBuf::from(".").join(&name);
    if cwd_lib.is_file() {
        out.push(cwd_lib);
    }
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf))
    {
        let plain = dir.join(&name);
        if plain.is_file() {
            out.push(plain);
        }
        // Versioned names as the wheel ships them (libonnxruntime.so.1.32.0), newest first.
        if let Ok(rd) = std::fs::read_dir(&dir) {
            let prefix = format!("{name}.");
            let mut versioned: Vec<PathBuf> = rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.is_file()
                        && p.file_name()
                            .and_then(|f| f.to_str())
                            .is_some_and(|f| f.starts_with(&prefix))
                })
                .collect();
            versioned.sort();
            out.extend(versioned.into_iter().rev());
        }
    }
    // System loader (dlopen search path).
    out.push(PathBuf::from(&name));
    out.push(PathBuf::from(format!("{name}.1")));
    Ok(out)
}

/// Process-wide ONNX Runtime state: the library is loaded once, one environment per process.
struct Runtime {
    env: Environment,
    library: PathBuf,
}

static RUNTIME: OnceLock<Runtime> = OnceLock::new();
static INIT_LOCK: Mutex<()> = Mutex::new(());

fn try_load(path: &Path) -> std::result::Result<Environment, String> {
    // `ort::init_from` reports load failures as errors; guard against panics inside the C API
    // glue (null pointers from a broken library) all the same.
    let path = path.to_path_buf();
    let res = std::panic::catch_unwind(move || -> std::result::Result<Environment, String> {
        let builder = ort::init_from(&path).map_err(|e| e.to_string())?;
        builder
            .with_name("moma-depth")
            .with_telemetry(false)
            .build()
            .map_err(|e| e.to_string())
    });
    match res {
        Ok(r) => r,
        Err(panic) => Err(panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| (*s).to_string()))
            .unwrap_or_else(|| "panic while loading the library".into())),
    }
}

fn runtime_with(explicit: Option<&Path>) -> Result<&'static Runtime> {
    if let Some(rt) = RUNTIME.get() {
        return Ok(rt);
    }
    let _guard = INIT_LOCK.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(rt) = RUNTIME.get() {
        return Ok(rt);
    }
    let candidates = match explicit {
        Some(p) if !p.is_file() => {
            return Err(DepthError::Unavailable(format!(
                "ONNX Runtime library not found: {} is not a file; {INSTALL_HINT}",
                p.display()
            )));
        }
        Some(p) => vec![p.to_path_buf()],
        None => library_candidates()?,
    };
    let mut failures = Vec::new();
    for cand in &candidates {
        match try_load(cand) {
            Ok(env) => {
                let rt = Runtime {
                    env,
                    library: cand.clone(),
                };
                return Ok(RUNTIME.get_or_init(|| rt));
            }
            Err(e) => failures.push(format!("  {}: {e}", cand.display())),
        }
    }
    Err(DepthError::Unavailable(format!(
        "cannot load the ONNX Runtime library; tried:\n{}\n{INSTALL_HINT}",
        failures.join("\n")
    )))
}

/// Loads the ONNX Runtime library from the documented locations (see the module docs) and creates
/// the process-wide environment; returns the library's path. Idempotent: later calls return the
/// library already loaded.
///
/// # Errors
/// [`DepthError::Unavailable`] with installation instructions when no usable library is found.
pub fn init_runtime() -> Result<PathBuf> {
    runtime_with(None).map(|rt| rt.library.clone())
}

/// As [`init_runtime`], but from an explicit library file (only effective before the runtime was
/// first loaded in this process; afterwards the already-loaded library's path is returned).
///
/// # Errors
/// [`DepthError::Unavailable`] when `path` is not a loadable ONNX Runtime ≥ 1.17 library.
pub fn init_runtime_from(path: impl AsRef<Path>) -> Result<PathBuf> {
    runtime_with(Some(path.as_ref())).map(|rt| rt.library.clone())
}

/// Whether an ONNX Runtime library can be loaded (loads it if not yet loaded).
pub fn runtime_available() -> bool {
    init_runtime().is_ok()
}

/// Build information of the loaded ONNX Runtime library (`ORT Build Info: git-branch=rel-1.32.0, …`).
///
/// # Errors
/// As [`init_runtime`].
pub fn runtime_info() -> Result<String> {
    init_runtime()?;
    Ok(ort::info().to_string())
}

/// Graph optimisation level of an ONNX Runtime session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OptimizationLevel {
    /// No graph optimisation.
    Disable,
    /// Basic (constant folding, redundant-node elimination).
    Basic,
    /// Extended (operator fusions: attention, GELU, LayerNorm, …).
    Extended,
    /// Everything, including layout optimisations (NCHWc) — ONNX Runtime's `ORT_ENABLE_ALL`,
    /// Python's default.
    All,
}

impl From<OptimizationLevel> for GraphOptimizationLevel {
    fn from(l: OptimizationLevel) -> Self {
        match l {
            OptimizationLevel::Disable => Self::Disable,
            OptimizationLevel::Basic => Self::Level1,
            OptimizationLevel::Extended => Self::Level2,
            OptimizationLevel::All => Self::All,
        }
    }
}

/// Session options of the ONNX backend.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OnnxOptions {
    /// Threads within an operator; `None` = the number of available cores.
    pub intra_threads: Option<usize>,
    /// Threads across operators (sequential execution when 1).
    pub inter_threads: usize,
    /// Graph optimisation level (default [`OptimizationLevel::All`]).
    pub optimization_level: OptimizationLevel,
    /// Memory-pattern planning (default on; the input shape of a depth model is fixed per session).
    pub memory_pattern: bool,
    /// Let idle intra-op threads spin (default on: lowest latency; off saves CPU between frames).
    pub intra_op_spinning: bool,
    /// Flush denormal floats to zero (default off).
    pub flush_to_zero: bool,
    /// Write the optimised graph here (`.onnx` or `.ort`), e.g. to inspect it or to load it faster
    /// later with [`OptimizationLevel::Disable`].
    pub optimized_model_path: Option<PathBuf>,
}

impl Default for OnnxOptions {
    fn default() -> Self {
        Self {
            intra_threads: None,
            inter_threads: 1,
            optimization_level: OptimizationLevel::All,
            memory_pattern: true,
            intra_op_spinning: true,
            flush_to_zero: false,
            optimized_model_path: None,
        }
    }
}

/// A Depth Anything V2 ONNX export run by ONNX Runtime on the CPU.
///
/// The model must have one `float32` input `(1, 3, H, W)` (named `image` in the official exports;
/// H and W fixed or dynamic) and a `float32` output `(1, H', W')` or `(1, 1, H', W')`.
pub struct OnnxDepthModel {
    session: Session,
    spec: ModelSpec,
    path: PathBuf,
    input_name: String,
    output_name: String,
    input_shape: Vec<i64>,
    output_shape: Vec<i64>,
    library: PathBuf,
}

impl std::fmt::Debug for OnnxDepthModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxDepthModel")
            .field("path", &self.path)
            .field("spec", &self.spec)
            .field("input", &(&self.input_name, &self.input_shape))
            .field("output", &(&self.output_name, &self.output_shape))
            .field("library", &self.library)
            .finish_non_exhaustive()
    }
}

fn backend<E: Into<ort::Error>>(what: &str) -> impl FnOnce(E) -> DepthError + '_ {
    move |e| DepthError::Onnx {
        context: what.to_string(),
        source: e.into(),
    }
}

fn fmt_shape(s: &[i64]) -> String {
    let dims: Vec<String> = s
        .iter()
        .map(|&d| if d < 0 { "?".into() } else { d.to_string() })
        .collect();
    format!("({})", dims.join(", "))
}

fn tensor_info(ty: &ValueType, what: &str, path: &Path) -> Result<(TensorElementType, Vec<i64>)> {
    match ty {
        ValueType::Tensor { ty, shape, .. } => Ok((*ty, shape.iter().copied().collect())),
        other => Err(DepthError::Weights {
            path: path.display().to_string(),
            reason: format!("the model's {what} is not a tensor ({other:?})"),
        }),
    }
}

impl OnnxDepthModel {
    /// Loads an ONNX export with explicit session options ([`OnnxOptions::default`]: all graph
    /// optimisations, one intra-op thread per core). Applications call [`crate::load`].
    ///
    /// # Errors
    /// [`DepthError::Unavailable`] without an ONNX Runtime library; [`DepthError::Weights`] for a
    /// missing/invalid file or a model whose inputs/outputs are not those of a depth model.
    pub fn load(path: impl AsRef<Path>, spec: ModelSpec, options: &OnnxOptions) -> Result<Self> {
        let path = path.as_ref();
        let weights_err = |reason: String| DepthError::Weights {
            path: path.display().to_string(),
            reason,
        };
        if !path.is_file() {
            return Err(weights_err("no such file".into()));
        }
        crate::weights_limits::check_weights_file_size(path)?;
        let rt = runtime_with(None)?;
        let intra = options
            .intra_threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
            .max(1);
        let mut builder = Session::builder(&rt.env)
            .map_err(backend("session options"))?
            .with_optimization_level(options.optimization_level.into())
            .map_err(backend("optimisation level"))?
            .with_intra_threads(intra)
            .map_err(backend("intra-op threads"))?
            .with_inter_threads(options.inter_threads.max(1))
            .map_err(backend("inter-op threads"))?
            .with_parallel_execution(options.inter_threads > 1)
            .map_err(backend("execution mode"))?
            .with_memory_pattern(options.memory_pattern)
            .map_err(backend("memory pattern"))?
            .with_intra_op_spinning(options.intra_op_spinning)
            .map_err(backend("intra-op spinning"))?;
        if options.flush_to_zero {
            builder = builder
                .with_flush_to_zero()
                .map_err(backend("flush to zero"))?;
        }
        if let Some(p) = &options.optimized_model_path {
            builder = builder
                .with_optimized_model_path(p)
                .map_err(backend("optimised model path"))?;
        }
        let session = builder
            .commit_from_file(path)
            .map_err(|source| DepthError::Onnx {
                context: format!("cannot load the model {}", path.display()),
                source,
            })?;

        if session.inputs().len() != 1 {
            return Err(weights_err(format!(
                "expected one input (the image), the model has {}",
                session.inputs().len()
            )));
        }
        if session.outputs().is_empty() {
            return Err(weights_err("the model has no output".into()));
        }
        let input = &session.inputs()[0];
        let output = &session.outputs()[0];
        let (in_ty, input_shape) = tensor_info(input.dtype(), "input", path)?;
        let (out_ty, output_shape) = tensor_info(output.dtype(), "output", path)?;
        if in_ty != TensorElementType::Float32 || out_ty != TensorElementType::Float32 {
            return Err(weights_err(format!(
                "expected float32 input and output, the model has {in_ty:?} -> {out_ty:?} \
                 (export the model in float32; float16 weights with Cast nodes are fine)"
            )));
        }
        let in_ok = input_shape.len() == 4
            && matches!(input_shape[0], 1 | -1)
            && matches!(input_shape[1], 3 | -1);
        if !in_ok {
            return Err(weights_err(format!(
                "expected input `{}` of shape (1, 3, H, W), the model has {}",
                input.name(),
                fmt_shape(&input_shape)
            )));
        }
        let out_ok = match output_shape.len() {
            3 => matches!(output_shape[0], 1 | -1),
            4 => matches!(output_shape[0], 1 | -1) && matches!(output_shape[1], 1 | -1),
            2 => true,
            _ => false,
        };
        if !out_ok {
            return Err(weights_err(format!(
                "expected output `{}` of shape (1, H, W) or (1, 1, H, W), the model has {}",
                output.name(),
                fmt_shape(&output_shape)
            )));
        }
        Ok(Self {
            input_name: input.name().to_string(),
            output_name: output.name().to_string(),
            input_shape,
            output_shape,
            session,
            spec,
            path: path.to_path_buf(),
            library: rt.library.clone(),
        })
    }

    /// Path of the model file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Name of the model's input (`image` in the official exports).
    pub fn input_name(&self) -> &str {
        &self.input_name
    }

    /// Name of the model's (first) output (`depth` in the official exports).
    pub fn output_name(&self) -> &str {
        &self.output_name
    }

    /// Declared input shape `(1, 3, H, W)`; `-1` marks a dynamic dimension.
    pub fn input_shape(&self) -> &[i64] {
        &self.input_shape
    }

    /// Declared output shape; `-1` marks a dynamic dimension.
    pub fn output_shape(&self) -> &[i64] {
        &self.output_shape
    }

    /// `(H, W)` when the export has a fixed spatial input size.
    pub fn fixed_input_hw(&self) -> Option<(usize, usize)> {
        match (self.input_shape[2], self.input_shape[3]) {
            (h, w) if h > 0 && w > 0 => Some((h as usize, w as usize)),
            _ => None,
        }
    }

    /// The ONNX Runtime library this process loaded.
    pub fn library(&self) -> &Path {
        &self.library
    }
}

impl DepthModel for OnnxDepthModel {
    fn spec(&self) -> ModelSpec {
        self.spec
    }

    fn runtime(&self) -> String {
        format!(
            "onnxruntime, CPU execution provider, {}",
            self.library.display()
        )
    }

    fn forward_net(&mut self, input: &Array3<f32>) -> Result<Array2<f32>> {
        let (c, h, w) = input.dim();
        if c != 3 || h == 0 || w == 0 {
            return Err(DepthError::Shape(format!(
                "expected a (3, H, W) input, got ({c}, {h}, {w})"
            )));
        }
        for (axis, (got, want)) in [
            (2usize, (h, self.input_shape[2])),
            (3, (w, self.input_shape[3])),
        ] {
            if want > 0 && got as i64 != want {
                let (fh, fw) = (self.input_shape[2], self.input_shape[3]);
                return Err(DepthError::Shape(format!(
                    "{} has a fixed input size {fh}x{fw} (H x W) but the pre-processed input is \
                     {h}x{w} (axis {axis} differs); set the input size to {} (`--input-size`, \
                     `input_size=`) with images of the matching aspect ratio, or use an export \
                     with dynamic height/width",
                    self.path.display(),
                    fh.min(fw)
                )));
            }
        }
        let contiguous = input.as_standard_layout();
        let data = contiguous
            .as_slice()
            .ok_or_else(|| DepthError::Backend("input is not contiguous".into()))?;
        let tensor = TensorRef::from_array_view(([1usize, 3, h, w], data))
            .map_err(backend("input tensor"))?;
        let outputs = self
            .session
            .run(ort::inputs![self.input_name.as_str() => tensor])
            .map_err(backend("run"))?;
        let value = outputs
            .get(&self.output_name)
            .ok_or_else(|| DepthError::Backend(format!("no output `{}`", self.output_name)))?;
        let (shape, data) = value
            .try_extract_tensor::<f32>()
            .map_err(backend("output tensor"))?;
        let dims: Vec<i64> = shape.iter().copied().collect();
        let (oh, ow) = match dims.as_slice() {
            [1, oh, ow] | [1, 1, oh, ow] | [oh, ow] => (*oh as usize, *ow as usize),
            _ => {
                return Err(DepthError::Shape(format!(
                    "unexpected output shape {} (expected (1, H, W) or (1, 1, H, W))",
                    fmt_shape(&dims)
                )));
            }
        };
        Array2::from_shape_vec((oh, ow), data.to_vec())
            .map_err(|e| DepthError::Shape(e.to_string()))
    }
}

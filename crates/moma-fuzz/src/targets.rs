//! The fuzz targets: one parser entry point each, on bytes in memory.

use std::path::Path;

/// A parser under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Target {
    /// `moma_io::png16_from_bytes`: uint16 depth PNGs (millimetres).
    DepthPng,
    /// `moma_io::npy_f32_from_bytes`: float depth / prediction `.npy`.
    Npy,
    /// `moma_io::pfm_from_bytes`: float depth / prediction PFM.
    Pfm,
    /// `moma_io::mask_from_bytes`: mask PNGs (any pixel type).
    Mask,
    /// `moma_io::rgb_from_bytes`: RGB images (PNG or JPEG).
    Rgb,
    /// `moma_io::parse_camera`: `camera.json`.
    Camera,
    /// `moma_io::parse_calibration`: calibration files.
    Calibration,
    /// `moma_depth::weights_limits::check_safetensors_header`: the input's first 8 bytes are the
    /// claimed file length (u64 little-endian), the rest the start of the file.
    Safetensors,
}

impl Target {
    /// Every target, in the order `all` runs them.
    pub const ALL: [Target; 8] = [
        Target::DepthPng,
        Target::Npy,
        Target::Pfm,
        Target::Mask,
        Target::Rgb,
        Target::Camera,
        Target::Calibration,
        Target::Safetensors,
    ];

    /// The target's name on the command line and in findings.
    pub fn name(self) -> &'static str {
        match self {
            Target::DepthPng => "depth-png",
            Target::Npy => "npy",
            Target::Pfm => "pfm",
            Target::Mask => "mask",
            Target::Rgb => "rgb",
            Target::Camera => "camera-json",
            Target::Calibration => "calibration-json",
            Target::Safetensors => "safetensors-header",
        }
    }

    /// The target called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|t| t.name() == name)
    }

    /// Whether inputs are PNG files (their chunk CRCs are repaired after mutation, most of the time).
    pub fn is_png(self) -> bool {
        matches!(self, Target::DepthPng | Target::Mask | Target::Rgb)
    }

    /// Runs the parser on `data`. Returns `Ok` when it accepted the input and `Err(message)` when
    /// it refused it: both are fine; only a panic, an abort or a hang is a finding.
    ///
    /// # Errors
    /// The parser's error message.
    pub fn run(self, data: &[u8]) -> Result<(), String> {
        let name = |ext: &str| Path::new("fuzz-input").with_extension(ext);
        let text = || std::str::from_utf8(data).map_err(|e| format!("not UTF-8: {e}"));
        let s = |e: &dyn std::fmt::Display| e.to_string();
        match self {
            Target::DepthPng => moma_io::png16_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Npy => moma_io::npy_f32_from_bytes(&name("npy"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Pfm => moma_io::pfm_from_bytes(&name("pfm"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Mask => moma_io::mask_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Rgb => moma_io::rgb_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Camera => moma_io::parse_camera(&name("json"), text()?)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Calibration => moma_io::parse_calibration(&name("json"), text()?)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Safetensors => {
                let (len, prefix) = data.split_at_checked(8).ok_or("shorter than 8 bytes")?;
                let mut n = [0u8; 8];
                n.copy_from_slice(len);
                let file_len = u64::from_le_bytes(n);
                moma_depth::weights_limits::check_safetensors_header(
                    &name("safetensors"),
                    prefix,
                    file_len,
                )
                .map(drop)
                .map_err(|e| s(&e))
            }
        }
    }
}

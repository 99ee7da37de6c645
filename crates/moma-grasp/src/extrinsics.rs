//! Camera → robot-base rigid transform.

use nalgebra::{Matrix3, Matrix4, Vector3};
use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::error::{GraspError, Result};

/// Tolerance on `RᵀR = I` (max abs entry) and `det R = 1`.
pub const RIGID_TOLERANCE: f64 = 1e-3;

/// A rigid transform taking camera-frame points (metres) to the robot base frame:
/// `p_base = R p_cam + t`, stored as the 4×4 row-major matrix `[[R, t], [0 0 0 1]]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "[[f64; 4]; 4]", into = "[[f64; 4]; 4]")]
pub struct Extrinsics {
    rows: [[f64; 4]; 4],
}

impl TryFrom<[[f64; 4]; 4]> for Extrinsics {
    type Error = GraspError;
    fn try_from(rows: [[f64; 4]; 4]) -> Result<Self> {
        Self::new(rows)
    }
}

impl From<Extrinsics> for [[f64; 4]; 4] {
    fn from(e: Extrinsics) -> Self {
        e.rows
    }
}

/// Largest camera-to-base translation accepted, metres. A camera that a robot grasps by sits
/// within the arm's reach of its base (a gantry's a few metres); a translation of hundreds is
/// millimetres given as metres, which would place every grasp 1 000 × too far.
pub const MAX_TRANSLATION_M: f64 = 20.0;

impl Extrinsics {
    /// Checks and wraps a camera→base matrix given as 4 rows.
    ///
    /// # Errors
    /// [`GraspError::NonRigidExtrinsics`] when an entry is not finite, the translation is beyond
    /// [`MAX_TRANSLATION_M`], the last row is not
    /// `0 0 0 1`, the rotation is not orthonormal within [`RIGID_TOLERANCE`], or `det R ≠ +1`
    /// (a reflection).
    pub fn new(rows: [[f64; 4]; 4]) -> Result<Self> {
        if rows.iter().flatten().any(|v| !v.is_finite()) {
            return Err(GraspError::NonRigidExtrinsics(
                "an entry is not a finite number".into(),
            ));
        }
        // a robot's base is within metres of its camera: millimetres would place grasps 1 000 ×
        // too far (and a translation beyond f32's range wrote `null` coordinates into the
        // grasps' JSON, poses being f32)
        let t = [rows[0][3], rows[1][3], rows[2][3]];
        if t.iter().any(|v| v.abs() > MAX_TRANSLATION_M) {
            return Err(GraspError::NonRigidExtrinsics(format!(
                "the translation {t:?} is beyond {MAX_TRANSLATION_M} m: not metres between a \
                 camera and its robot's base (millimetres? the translation is in metres)"
            )));
        }
        if rows[3] != [0.0, 0.0, 0.0, 1.0] {
            return Err(GraspError::NonRigidExtrinsics(format!(
                "the last row is {:?}, expected [0, 0, 0, 1]",
                rows[3]
            )));
        }
        let r = Matrix3::from_fn(|i, j| rows[i][j]);
        let err = (r.transpose() * r - Matrix3::identity()).abs().max();
        if err > RIGID_TOLERANCE {
            return Err(GraspError::NonRigidExtrinsics(format!(
                "the rotation block is not orthonormal (|RᵀR − I| max = {err:.3e}, tolerance {RIGID_TOLERANCE:e})"
            )));
        }
        let det = r.determinant();
        if (det - 1.0).abs() > RIGID_TOLERANCE {
            return Err(GraspError::NonRigidExtrinsics(format!(
                "det R = {det:.4}, expected +1 (a reflection is not a rigid transform)"
            )));
        }
        Ok(Self { rows })
    }

    /// The identity (base frame = camera frame).
    pub fn identity() -> Self {
        let m = Matrix4::<f64>::identity();
        Self {
            rows: std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)])),
        }
    }

    /// The 4 rows.
    pub fn rows(&self) -> [[f64; 4]; 4] {
        self.rows
    }

    fn rotate(&self, v: &Vec3) -> Vector3<f64> {
        let v = v.cast::<f64>();
        Vector3::from_fn(|i, _| {
            self.rows[i][0] * v.x + self.rows[i][1] * v.y + self.rows[i][2] * v.z
        })
    }

    /// Maps a camera-frame point (metres) to the base frame.
    pub fn point(&self, p: &Vec3) -> Vec3 {
        let r = self.rotate(p) + Vector3::new(self.rows[0][3], self.rows[1][3], self.rows[2][3]);
        r.cast::<f32>()
    }

    /// Maps a camera-frame direction to the base frame (rotation only).
    pub fn direction(&self, d: &Vec3) -> Vec3 {
        self.rotate(d).cast::<f32>()
    }
}

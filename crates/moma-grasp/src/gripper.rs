//! Gripper geometry: a parallel jaw (default Robotiq 2F-85) and a suction cup.

use serde::{Deserialize, Serialize};

use crate::error::{GraspError, Result, positive};

/// Largest gripper dimension accepted, metres. Parallel grippers open at most a few decimetres
/// (Robotiq 2F-140: 0.14 m) and suction tools are shorter than a metre. The planner marches along
/// the jaws and the cup's axis in millimetre steps, so a size read from a file must be bounded:
/// a stroke of 1e30 m would never finish.
pub const MAX_GRIPPER_SIZE_M: f32 = 1.0;

/// A gripper dimension (or a grasp width): finite, > 0 and at most [`MAX_GRIPPER_SIZE_M`];
/// `err` builds the error naming it.
pub(crate) fn gripper_size(name: &str, value: f32, err: fn(String) -> GraspError) -> Result<()> {
    positive(name, value, err)?;
    if value > MAX_GRIPPER_SIZE_M {
        return Err(err(format!(
            "{name} = {value} m is larger than any gripper (at most {MAX_GRIPPER_SIZE_M} m)"
        )));
    }
    Ok(())
}

/// A parallel-jaw gripper in its grasp frame: origin at the grasp centre (midpoint of the two
/// contacts), `x` = approach, `y` = closing axis, `z = x × y` ("height" of the fingers).
///
/// The finger pads' contact line is the `y` axis; each fingertip reaches `contact_to_tip_m` past
/// it along the approach; a finger spans `x ∈ [contact_to_tip_m − finger_length_m,
/// contact_to_tip_m]`, `|y| ∈ [w/2, w/2 + finger_thickness_m]`, `|z| ≤ finger_height_m / 2` for an
/// opening `w`; the palm spans the `palm_depth_m` behind the fingers over the whole width. Defaults:
/// Robotiq 2F-85 as graspnetAPI models it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ParallelJaw {
    /// Largest opening, metres. Default 0.085 m.
    pub stroke_m: f32,
    /// Finger extent across the closing plane (along `z`), metres. Default 0.02 m.
    pub finger_height_m: f32,
    /// Finger thickness along the closing axis, metres. Default 0.01 m.
    pub finger_thickness_m: f32,
    /// Finger length along the approach, metres. Default 0.04 m.
    pub finger_length_m: f32,
    /// Palm depth along the approach, behind the fingers, metres. Default 0.02 m.
    pub palm_depth_m: f32,
    /// How far the fingertips reach past the contact line along the approach, metres.
    /// Default 0.01 m.
    pub contact_to_tip_m: f32,
    /// Free space the planner leaves between each finger and its contact before closing, metres:
    /// opening = contact distance + 2 × this, capped at the stroke. Default 0.01 m.
    pub opening_clearance_m: f32,
}

impl Default for ParallelJaw {
    fn default() -> Self {
        Self {
            stroke_m: 0.085,
            finger_height_m: 0.02,
            finger_thickness_m: 0.01,
            finger_length_m: 0.04,
            palm_depth_m: 0.02,
            contact_to_tip_m: 0.01,
            opening_clearance_m: 0.01,
        }
    }
}

impl ParallelJaw {
    /// Checks every size is finite, positive and at most [`MAX_GRIPPER_SIZE_M`], and the tips
    /// lie on the fingers.
    ///
    /// # Errors
    /// [`GraspError::InvalidGripper`] naming the field.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("stroke_m", self.stroke_m),
            ("finger_height_m", self.finger_height_m),
            ("finger_thickness_m", self.finger_thickness_m),
            ("finger_length_m", self.finger_length_m),
            ("palm_depth_m", self.palm_depth_m),
            ("contact_to_tip_m", self.contact_to_tip_m),
            ("opening_clearance_m", self.opening_clearance_m),
        ] {
            gripper_size(name, v, GraspError::InvalidGripper)?;
        }
        if self.contact_to_tip_m >= self.finger_length_m {
            return Err(GraspError::InvalidGripper(format!(
                "contact_to_tip_m = {} must be shorter than finger_length_m = {}",
                self.contact_to_tip_m, self.finger_length_m
            )));
        }
        Ok(())
    }
}

/// A suction cup approaching along its axis.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SuctionCup {
    /// Cup radius (the seal ring), metres. Default 0.01 m.
    pub radius_m: f32,
    /// Axial compliance of the cup/bellows, metres: the surface may be hit this much before or after
    /// the planned point. Default 0.015 m.
    pub compliance_m: f32,
    /// Length of the tool (cup + shaft) behind the cup whose cylinder of `radius_m` must be free,
    /// metres. Default 0.1 m.
    pub tool_length_m: f32,
}

impl Default for SuctionCup {
    fn default() -> Self {
        Self {
            radius_m: 0.01,
            compliance_m: 0.015,
            tool_length_m: 0.1,
        }
    }
}

impl SuctionCup {
    /// Checks every size is finite and positive.
    ///
    /// # Errors
    /// [`GraspError::InvalidGripper`] naming the field (every size finite, > 0 and at most
    /// [`MAX_GRIPPER_SIZE_M`]).
    pub fn validate(&self) -> Result<()> {
        gripper_size("radius_m", self.radius_m, GraspError::InvalidGripper)?;
        gripper_size(
            "compliance_m",
            self.compliance_m,
            GraspError::InvalidGripper,
        )?;
        gripper_size(
            "tool_length_m",
            self.tool_length_m,
            GraspError::InvalidGripper,
        )
    }
}

/// Either gripper.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Gripper {
    /// A parallel jaw.
    Parallel(ParallelJaw),
    /// A suction cup.
    Suction(SuctionCup),
}

/// Which kind of gripper, by the names that the JSON `kind`, `--gripper` and Python's
/// `gripper=` use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GripperKind {
    /// Two-finger parallel jaw.
    Parallel,
    /// Vacuum cup.
    Suction,
}

impl GripperKind {
    /// Both kinds.
    pub const ALL: [GripperKind; 2] = [GripperKind::Parallel, GripperKind::Suction];

    /// `parallel` or `suction`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Parallel => "parallel",
            Self::Suction => "suction",
        }
    }

    /// The gripper of this kind with its default geometry ([`ParallelJaw::default`]: Robotiq
    /// 2F-85; [`SuctionCup::default`]: 10 mm radius, 15 mm compliance).
    pub fn default_gripper(self) -> Gripper {
        match self {
            Self::Parallel => Gripper::Parallel(ParallelJaw::default()),
            Self::Suction => Gripper::Suction(SuctionCup::default()),
        }
    }
}

impl std::fmt::Display for GripperKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for GripperKind {
    type Err = GraspError;
    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|g| g.name() == s)
            .ok_or_else(|| GraspError::UnknownGripper(s.to_string()))
    }
}

impl Gripper {
    /// The gripper's kind.
    pub const fn kind(&self) -> GripperKind {
        match self {
            Gripper::Parallel(_) => GripperKind::Parallel,
            Gripper::Suction(_) => GripperKind::Suction,
        }
    }

    /// `parallel` or `suction` (the JSON `kind`).
    pub const fn kind_name(&self) -> &'static str {
        self.kind().name()
    }

    /// Validates the geometry.
    ///
    /// # Errors
    /// [`GraspError::InvalidGripper`].
    pub fn validate(&self) -> Result<()> {
        match self {
            Gripper::Parallel(j) => j.validate(),
            Gripper::Suction(c) => c.validate(),
        }
    }
}

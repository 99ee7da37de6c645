//! Grasp execution on a depth scene: the rules of docs/method.md §8 shared by the planners and the
//! proxy scorer (one implementation, so planning and scoring use the same convention).

use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::error::{GraspError, Result, positive};
use crate::grasp::FailureReason;
use crate::gripper::{MAX_GRIPPER_SIZE_M, ParallelJaw, SuctionCup};
use crate::scene::Scene;

/// The friction coefficients GraspNet reports against, ascending.
pub const MU_GRID: [f32; 6] = [0.2, 0.4, 0.6, 0.8, 1.0, 1.2];

/// The execution rules (docs/method.md §8) with their documented defaults.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ExecConfig {
    /// Step when marching along a closing line or an approach ray, metres. Default 0.001 m.
    pub march_step_m: f32,
    /// A 3-D point counts as inside the (2.5-D, solid-behind-the-surface) scene when it is at most
    /// this much in front of the observed surface at its pixel, metres. Default 0.002 m.
    pub occupancy_tol_m: f32,
    /// Radius of the disc giving a silhouette contact's normal, pixels. Default 3.
    pub silhouette_radius_px: usize,
    /// A contact counts as on the object when an object pixel lies within this many pixels of it
    /// (masks and depth edges of real frames disagree by a pixel or two). Default 2.
    pub object_tolerance_px: usize,
    /// A parallel grasp collides when at least this many points lie inside a finger or the palm.
    /// Default 1 (graspnetAPI).
    pub collision_min_points: usize,
    /// A parallel grasp is empty when fewer points than this lie between the fingers. Default 10.
    pub empty_min_points: usize,
    /// Angular bins of the suction seal ring. Default 72.
    pub seal_bins: usize,
    /// A seal ring bin is empty when the observed surface there is farther than this from the
    /// contact plane (along the approach), or missing, metres. Default 0.005 m.
    pub seal_max_gap_m: f32,
    /// The seal breaks when a point inside the ring stands more than this above the contact plane,
    /// metres. Default 0.005 m.
    pub seal_max_bump_m: f32,
    /// Seal quality = exp(−scale · var(ring heights in m)). Default 1e5 (SuctionNet / Dex-Net 3.0).
    pub seal_variance_scale: f32,
    /// Largest angle between the suction approach and the (inward) surface normal, degrees.
    /// Default 30.
    pub max_approach_angle_deg: f32,
}

impl Default for ExecConfig {
    fn default() -> Self {
        Self {
            march_step_m: 0.001,
            occupancy_tol_m: 0.002,
            silhouette_radius_px: 3,
            object_tolerance_px: 2,
            collision_min_points: 1,
            empty_min_points: 10,
            seal_bins: 72,
            seal_max_gap_m: 0.005,
            seal_max_bump_m: 0.005,
            seal_variance_scale: 1e5,
            max_approach_angle_deg: 30.0,
        }
    }
}

/// Smallest march step accepted, metres (0.1 mm: far below depth noise), so that the marches
/// over the largest gripper ([`crate::gripper::MAX_GRIPPER_SIZE_M`]) stay in the tens of
/// thousands of steps (about 20 000 along the jaws, 40 000 along a suction cup's axis).
pub const MIN_MARCH_STEP_M: f32 = 1e-4;

impl ExecConfig {
    /// Checks the rules.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let e = GraspError::InvalidConfig;
        positive("march_step_m", self.march_step_m, e)?;
        if self.march_step_m < MIN_MARCH_STEP_M {
            return Err(GraspError::InvalidConfig(format!(
                "march_step_m = {} m is below {MIN_MARCH_STEP_M} m: with grippers up to \
                 {MAX_GRIPPER_SIZE_M} m a march would take over {} steps",
                self.march_step_m,
                (MAX_GRIPPER_SIZE_M / MIN_MARCH_STEP_M) as u32
            )));
        }
        positive("occupancy_tol_m", self.occupancy_tol_m, e)?;
        positive("seal_max_gap_m", self.seal_max_gap_m, e)?;
        positive("seal_max_bump_m", self.seal_max_bump_m, e)?;
        positive("seal_variance_scale", self.seal_variance_scale, e)?;
        positive("max_approach_angle_deg", self.max_approach_angle_deg, e)?;
        if self.seal_bins < 8 || self.collision_min_points == 0 || self.silhouette_radius_px == 0 {
            return Err(GraspError::InvalidConfig(
                "seal_bins must be >= 8, collision_min_points and silhouette_radius_px >= 1".into(),
            ));
        }
        Ok(())
    }
}

/// A parallel-jaw pose with unit `approach ⟂ closing` (camera frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct JawPose {
    pub center: Vec3,
    pub approach: Vec3,
    pub closing: Vec3,
    pub width: f32,
}

/// Planner-only tolerances for soft, noisy (predicted) depth; the scorer uses none.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Soft {
    /// Silhouette when a pixel within this many pixels is farther by more than `jump_m`.
    pub window_px: usize,
    /// Depth drop over the window that makes a silhouette, metres.
    pub jump_m: f32,
    /// Disc radius of the silhouette normal, pixels.
    pub radius_px: usize,
    /// Fingertips shortened by this in the collision test, metres.
    pub collision_margin_m: f32,
}

/// A contact found by closing a finger.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Contact {
    pub point: Vec3,
    pub normal: Option<Vec3>,
    pub index: usize,
}

/// Outcome of executing a parallel grasp.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ParallelExec {
    pub failure: Option<FailureReason>,
    /// Smallest μ of [`MU_GRID`] that passes the friction test (when the contacts were found).
    pub min_mu: Option<f32>,
    /// `tan` of the larger contact-normal angle.
    pub mu_needed: f32,
    pub contacts: Option<[Contact; 2]>,
}

impl Scene {
    /// Pixel of `q` when `q` lies inside the scene: at most `tol` in front of the observed surface
    /// (everything behind an observed surface is solid; holes and off-image rays are free).
    #[inline]
    pub(crate) fn occupied(&self, q: &Vec3, tol: f32) -> Option<usize> {
        self.cloud
            .project(q)
            .filter(|&i| self.cloud.valid[i] && q.z >= self.cloud.points[i].z - tol)
    }

    /// `i` if valid, else the first valid pixel of its 3×3 neighbourhood (isolated holes do not
    /// empty a seal bin).
    pub(crate) fn valid_near(&self, i: usize) -> Option<usize> {
        let c = &self.cloud;
        if c.valid[i] {
            return Some(i);
        }
        let (u, v) = (i % c.width, i / c.width);
        for nv in v.saturating_sub(1)..=(v + 1).min(c.height - 1) {
            for nu in u.saturating_sub(1)..=(u + 1).min(c.width - 1) {
                let j = c.index(nu, nv);
                if c.valid[j] {
                    return Some(j);
                }
            }
        }
        None
    }

    /// Whether an object pixel lies within `r` pixels (Chebyshev) of pixel `i`.
    pub(crate) fn near_object(&self, i: usize, r: usize) -> bool {
        let c = &self.cloud;
        let (u, v) = (i % c.width, i / c.width);
        (v.saturating_sub(r)..=(v + r).min(c.height - 1)).any(|nv| {
            (u.saturating_sub(r)..=(u + r).min(c.width - 1))
                .any(|nu| self.is_object(c.index(nu, nv)))
        })
    }

    /// Horizontal (⟂ up) outward normal of a silhouette at pixel `i`.
    pub(crate) fn silhouette_normal(&self, i: usize, radius_px: usize) -> Option<Vec3> {
        let d = self.cloud.silhouette_direction(i, radius_px)?;
        let up = self.up();
        let h = d - up * d.dot(&up);
        let n = h.norm();
        (n > 1e-3).then(|| h / n)
    }

    /// Horizontal outward normal of a soft silhouette at pixel `i` (planning only).
    pub(crate) fn soft_silhouette_normal(&self, i: usize, soft: &Soft) -> Option<Vec3> {
        let d = self
            .cloud
            .silhouette_direction_with(i, soft.radius_px, soft.jump_m)?;
        let up = self.up();
        let h = d - up * d.dot(&up);
        let n = h.norm();
        (n > 1e-3).then(|| h / n)
    }

    /// Marches from `start` along unit `dir` for `length` metres and returns the first point inside
    /// the scene. Contact normal (docs/method.md §8): when the previous sample was free because its pixel
    /// lies farther (or is a hole / off-image), the contact is on a silhouette and its normal is the
    /// horizontal depth-gradient normal pointing out of the object; otherwise it is the observed
    /// surface normal there.
    pub(crate) fn find_contact(
        &self,
        start: Vec3,
        dir: Vec3,
        length: f32,
        exec: &ExecConfig,
        soft: Option<&Soft>,
    ) -> Option<Contact> {
        let step = exec.march_step_m;
        let n_steps = (length / step).ceil() as usize;
        let mut prev: Option<Option<usize>> = None;
        for k in 0..=n_steps {
            let t = (k as f32 * step).min(length);
            let q = start + dir * t;
            let pix = self.cloud.project(&q);
            if let Some(i) = pix.filter(|&i| {
                self.cloud.valid[i] && q.z >= self.cloud.points[i].z - exec.occupancy_tol_m
            }) {
                let silhouette = match prev {
                    None => false,
                    Some(None) => true,
                    Some(Some(j)) => {
                        j != i
                            && (!self.cloud.valid[j]
                                || self.cloud.points[j].z
                                    > self.cloud.points[i].z + self.cloud.edge_jump_m)
                    }
                };
                let r = exec.silhouette_radius_px;
                let normal = if let Some(s) =
                    soft.filter(|s| silhouette || self.cloud.is_soft_edge(i, s.window_px, s.jump_m))
                {
                    self.soft_silhouette_normal(i, s).or(self.cloud.normal(i))
                } else if silhouette {
                    self.silhouette_normal(i, r).or(self.cloud.normal(i))
                } else {
                    self.cloud.normal(i).or(self.silhouette_normal(i, r))
                };
                return Some(Contact {
                    point: q,
                    normal,
                    index: i,
                });
            }
            prev = Some(pix);
        }
        None
    }

    /// Counts points in the fingers + palm (collision), between the fingers, and object points
    /// between the fingers.
    /// With `soft` (planning), points inside a soft silhouette ([`crate::OrganisedCloud`]'s mixed
    /// pixels) do not collide, until `mixed_until` other points already collide.
    pub(crate) fn scan_jaw(
        &self,
        pose: &JawPose,
        jaw: &ParallelJaw,
        soft: Option<&Soft>,
        mixed_until: usize,
    ) -> (usize, usize, usize) {
        let (c, a, b) = (pose.center, pose.approach, pose.closing);
        let hz = a.cross(&b);
        let half_h = jaw.finger_height_m / 2.0;
        let half_w = pose.width / 2.0;
        let outer = half_w + jaw.finger_thickness_m;
        let x_tip = jaw.contact_to_tip_m;
        let x_base = x_tip - jaw.finger_length_m;
        let x_back = x_base - jaw.palm_depth_m;
        let cloud = &self.cloud;
        let (mut u0, mut u1, mut v0, mut v1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        let mut full = false;
        for x in [x_back, x_tip] {
            for y in [-outer, outer] {
                for z in [-half_h, half_h] {
                    match cloud.project_uv(&(c + a * x + b * y + hz * z)) {
                        Some((u, v)) => {
                            u0 = u0.min(u);
                            u1 = u1.max(u);
                            v0 = v0.min(v);
                            v1 = v1.max(v);
                        }
                        None => full = true,
                    }
                }
            }
        }
        let (w, h) = (cloud.width as f32, cloud.height as f32);
        if full {
            (u0, u1, v0, v1) = (0.0, w - 1.0, 0.0, h - 1.0);
        }
        let u0 = (u0.floor() - 1.0).clamp(0.0, w - 1.0) as usize;
        let u1 = (u1.ceil() + 1.0).clamp(0.0, w - 1.0) as usize;
        let v0 = (v0.floor() - 1.0).clamp(0.0, h - 1.0) as usize;
        let v1 = (v1.ceil() + 1.0).clamp(0.0, h - 1.0) as usize;
        let (mut collide, mut between, mut between_obj) = (0, 0, 0);
        for v in v0..=v1 {
            let row = v * cloud.width;
            for i in row + u0..=row + u1 {
                if !cloud.valid[i] {
                    continue;
                }
                let d = cloud.points[i] - c;
                let x = d.dot(&a);
                if x < x_back || x > x_tip {
                    continue;
                }
                if d.dot(&hz).abs() > half_h {
                    continue;
                }
                let y = d.dot(&b).abs();
                if y > outer {
                    continue;
                }
                if x < x_base || y >= half_w {
                    // Mixed pixels are looked for only until the grasp collides anyway
                    // (`mixed_until` real collisions), which keeps colliding candidates cheap.
                    // They are excused beside the fingers only: a blend of the grasped object's
                    // silhouette lies below its top, never as high as the palm (in a bin, the
                    // steep inner face of a wall is "mixed" and was excused, and the palm went
                    // through the wall)
                    if x < x_base
                        || collide >= mixed_until
                        || !soft.is_some_and(|s| cloud.is_mixed(i, s.window_px, s.jump_m))
                    {
                        collide += 1;
                    }
                } else {
                    between += 1;
                    if self.labels_at(i) {
                        between_obj += 1;
                    }
                }
            }
        }
        (collide, between, between_obj)
    }

    #[inline]
    fn labels_at(&self, i: usize) -> bool {
        self.is_object(i)
    }

    /// Executes a parallel grasp (docs/method.md §8). Reasons in the order collision, empty, missed
    /// object, not antipodal at `mu`. With `early_exit` (planning), the cheap contact and friction
    /// tests run first and the first failure is returned. `soft` (planning only) recognises
    /// silhouettes spread over a few pixels and shortens the fingertips in the collision test.
    pub(crate) fn execute_parallel(
        &self,
        pose: &JawPose,
        jaw: &ParallelJaw,
        exec: &ExecConfig,
        mu: f32,
        early_exit: bool,
        soft: Option<&Soft>,
    ) -> ParallelExec {
        let half = pose.width / 2.0;
        let b = pose.closing;
        let c1 = self.find_contact(pose.center - b * half, b, half, exec, soft);
        let c2 = self.find_contact(pose.center + b * half, -b, half, exec, soft);
        let contacts = match (c1, c2) {
            (Some(x), Some(y))
                if self.near_object(x.index, exec.object_tolerance_px)
                    && self.near_object(y.index, exec.object_tolerance_px) =>
            {
                Some([x, y])
            }
            _ => None,
        };
        let mu_needed = contacts.map_or(f32::INFINITY, |[x, y]| friction_needed(&x, &y, &b));
        let min_mu = MU_GRID.iter().copied().find(|m| *m + 1e-6 >= mu_needed);
        let contact_failure = if contacts.is_none() {
            Some(FailureReason::MissedObject)
        } else if mu_needed > mu + 1e-6 {
            Some(FailureReason::NotAntipodal)
        } else {
            None
        };
        if early_exit && contact_failure.is_some() {
            return ParallelExec {
                failure: contact_failure,
                min_mu,
                mu_needed,
                contacts,
            };
        }
        let (collide, between, between_obj) = match soft {
            Some(s) if s.collision_margin_m > 0.0 => {
                let m = s.collision_margin_m.min(jaw.contact_to_tip_m);
                let short = ParallelJaw {
                    contact_to_tip_m: jaw.contact_to_tip_m - m,
                    finger_length_m: jaw.finger_length_m - m,
                    ..*jaw
                };
                self.scan_jaw(pose, &short, soft, exec.collision_min_points)
            }
            _ => self.scan_jaw(pose, jaw, soft, exec.collision_min_points),
        };
        let failure = if collide >= exec.collision_min_points {
            Some(FailureReason::Collision)
        } else if between < exec.empty_min_points {
            Some(FailureReason::Empty)
        } else if between_obj == 0 {
            Some(FailureReason::MissedObject)
        } else {
            contact_failure
        };
        let passed_geometry = !matches!(
            failure,
            Some(FailureReason::Collision | FailureReason::Empty | FailureReason::MissedObject)
        );
        ParallelExec {
            failure,
            min_mu: if passed_geometry { min_mu } else { None },
            mu_needed,
            contacts,
        }
    }

    /// Where the observed surface lies under ring point `q` along the approach `a` (the cup's
    /// lip meets it there): its height `(s − q) · a` (metres, positive = farther along the
    /// approach) and the pixel, or `None` when no surface lies within `gap` of `q` along `a`.
    ///
    /// The camera ray through `q` meets the surface at `q`'s own footprint only where it runs
    /// along `a`. So its point is taken only when it lies on `q`'s line within 2.5 pixel
    /// footprints (the projection's rounding and [`Self::valid_near`]'s neighbour). Otherwise
    /// (a tilted cup on a steep face, or a ring point over free air beside an object narrower
    /// than the cup) the line itself is followed from `−gap` to `+gap` in 0.5 mm steps to where
    /// it enters the observed surface: the ring's surface point, or none. Taken along the camera
    /// ray, a 10 mm cup "sealed" on 6 mm rods with half its ring over free air.
    fn ring_surface(&self, q: &Vec3, a: &Vec3, gap: f32) -> Option<(f32, usize)> {
        let c = &self.cloud;
        let seen = |x: &Vec3| c.project(x).and_then(|i| self.valid_near(i));
        let i = seen(q)?;
        let d = c.points[i] - q;
        let along = d.dot(a);
        let lateral = (d - a * along).norm();
        let s = c.points[i];
        let ray = s / s.norm().max(f32::MIN_POSITIVE);
        // a pixel's footprint at the point's depth, seen across the approach
        let footprint = s.z / c.fx / ray.dot(a).abs().max(0.5);
        if lateral <= 2.5 * footprint {
            return Some((along, i));
        }
        // the line through q along a enters the surface where a point of it first lies at or
        // behind the surface the camera sees (the start must be in front of it)
        const STEP_M: f32 = 0.0005;
        let steps = (2.0 * gap / STEP_M).ceil() as usize;
        let behind = |x: &Vec3| seen(x).filter(|&j| x.z >= c.points[j].z);
        if behind(&(q - a * gap)).is_some() {
            return None;
        }
        (1..=steps).find_map(|k| {
            let t = -gap + k as f32 * STEP_M;
            behind(&(q + a * t)).map(|j| (t, j))
        })
    }

    /// Seal test at surface point `p` for approach `a` (unit, into the surface): `Ok((quality,
    /// flatness))` or `Err(SealBroken)`. Quality = exp(−scale·var(ring heights)); flatness = mean
    /// over the ring of max(0, n · (−a)).
    pub(crate) fn seal(
        &self,
        p: &Vec3,
        a: &Vec3,
        cup: &SuctionCup,
        exec: &ExecConfig,
    ) -> std::result::Result<(f32, f32), FailureReason> {
        let (e1, e2) = perpendiculars(a);
        let bins = exec.seal_bins;
        let r = cup.radius_m;
        let (mut sum, mut sum2, mut flat) = (0.0f32, 0.0f32, 0.0f32);
        for k in 0..bins {
            let th = std::f32::consts::TAU * k as f32 / bins as f32;
            let q = p + (e1 * th.cos() + e2 * th.sin()) * r;
            // (p − q) · a = 0: the ring's height relative to the contact plane
            let Some((along, i)) = self.ring_surface(&q, a, exec.seal_max_gap_m) else {
                return Err(FailureReason::SealBroken);
            };
            let h = -along;
            if h.abs() > exec.seal_max_gap_m {
                return Err(FailureReason::SealBroken);
            }
            sum += h;
            sum2 += h * h;
            flat += self.cloud.normal(i).map_or(0.0, |n| (-n.dot(a)).max(0.0));
        }
        for frac in [1.0 / 3.0, 2.0 / 3.0] {
            for k in 0..12 {
                let th = std::f32::consts::TAU * (k as f32 + 0.5) / 12.0;
                let q = p + (e1 * th.cos() + e2 * th.sin()) * (r * frac);
                if let Some(i) = self.cloud.project(&q).filter(|&i| self.cloud.valid[i])
                    && (p - self.cloud.points[i]).dot(a) > exec.seal_max_bump_m
                {
                    return Err(FailureReason::SealBroken);
                }
            }
        }
        let n = bins as f32;
        let var = (sum2 / n - (sum / n).powi(2)).max(0.0);
        Ok(((-exec.seal_variance_scale * var).exp(), flat / n))
    }

    /// Executes a suction grasp at `point` with approach `a` (docs/method.md §8): the hit along the ray,
    /// then object, crash / reach, seal and approach-angle tests. Returns the failure, if any.
    pub(crate) fn execute_suction(
        &self,
        point: &Vec3,
        a: &Vec3,
        cup: &SuctionCup,
        exec: &ExecConfig,
    ) -> Option<FailureReason> {
        let step = exec.march_step_m * 0.5;
        let t0 = -(cup.compliance_m + 0.005);
        let n_steps = ((cup.compliance_m - t0) / step).ceil() as usize;
        let mut hit = None;
        for k in 0..=n_steps {
            let q = point + a * (t0 + k as f32 * step);
            if let Some(i) = self.occupied(&q, exec.occupancy_tol_m) {
                hit = Some(i);
                break;
            }
        }
        let Some(i) = hit else {
            return Some(FailureReason::NotReached);
        };
        if !self.is_object(i) {
            return Some(FailureReason::MissedObject);
        }
        let o = self.cloud.points[i];
        let t_hit = (o - point).dot(a);
        if t_hit < -cup.compliance_m {
            return Some(FailureReason::CupCrash);
        }
        if t_hit > cup.compliance_m {
            return Some(FailureReason::NotReached);
        }
        if let Err(f) = self.seal(&o, a, cup, exec) {
            return Some(f);
        }
        let max_cos = exec.max_approach_angle_deg.to_radians().cos();
        match self.cloud.normal(i) {
            Some(n) if (-n).dot(a) >= max_cos => None,
            _ => Some(FailureReason::ApproachAngle),
        }
    }
}

/// `tan` of the larger angle between each contact's outward normal and the contact line pointing
/// out of the object there (finger 1 closes along `+b`, finger 2 along `−b`).
fn friction_needed(c1: &Contact, c2: &Contact, b: &Vec3) -> f32 {
    let (Some(n1), Some(n2)) = (c1.normal, c2.normal) else {
        return f32::INFINITY;
    };
    let l = c2.point - c1.point;
    let l = if l.norm() > 1e-6 { l.normalize() } else { *b };
    let cos1 = n1.dot(&(-l)).clamp(-1.0, 1.0);
    let cos2 = n2.dot(&l).clamp(-1.0, 1.0);
    let ang = cos1.acos().max(cos2.acos());
    if ang >= std::f32::consts::FRAC_PI_2 - 1e-4 {
        f32::INFINITY
    } else {
        ang.tan()
    }
}

/// Two unit vectors completing unit `a` to a right-handed orthonormal basis.
pub(crate) fn perpendiculars(a: &Vec3) -> (Vec3, Vec3) {
    let helper = if a.x.abs() < 0.9 {
        Vec3::x()
    } else {
        Vec3::y()
    };
    let e1 = a.cross(&helper).normalize();
    let e2 = a.cross(&e1);
    (e1, e2)
}

//! What to show of planned grasps: colours by rank, the 3-D segments of an overlay (fingers and
//! closing line of a parallel jaw, the rim of a suction cup) and the boxes of a gripper mesh, in
//! the camera frame (metres). `moma-io` draws the segments on an image and writes the boxes into a
//! PLY; nothing here touches pixels or files.

use moma_core::shapes::{BoxMesh, Segment3};

use crate::cloud::Vec3;
use crate::contact::perpendiculars;
use crate::grasp::{Grasp, PlanOutcome};
use crate::gripper::Gripper;

/// Colour of rank `k` (0 = best) of `n` grasps: best green, then yellow to red.
pub fn rank_colour(k: usize, n: usize) -> [u8; 3] {
    if k == 0 {
        return [0, 230, 0];
    }
    let t = if n > 2 {
        (k - 1) as f32 / (n - 2) as f32
    } else {
        0.0
    };
    [255, (220.0 * (1.0 - t)) as u8, 0]
}

fn arr(v: Vec3) -> [f32; 3] {
    [v.x, v.y, v.z]
}

/// The overlay of `outcome`'s grasps, worst first so that the best is drawn last (on top): for a
/// parallel jaw the closing line between the fingers, each finger's extent across it (the best
/// one thicker) and 30 mm of the approach axis back from the centre (towards the palm), for a
/// suction cup its rim (36 chords) and 30 mm of its approach axis.
/// Grasps of the other gripper kind than `gripper` are skipped.
pub fn overlay_segments(outcome: &PlanOutcome, gripper: &Gripper) -> Vec<Segment3> {
    let n = outcome.grasps.len();
    let mut out = Vec::new();
    for (rank, g) in outcome.grasps.iter().enumerate().rev() {
        let colour = rank_colour(rank, n);
        let thick = if rank == 0 { 1 } else { 0 };
        let mut seg = |a: Vec3, b: Vec3, half_width_px: i64| {
            out.push(Segment3 {
                a_m: arr(a),
                b_m: arr(b),
                colour,
                half_width_px,
            });
        };
        match (g, gripper) {
            (Grasp::Parallel(p), Gripper::Parallel(jaw)) => {
                let (centre, a, b) = (
                    Vec3::from(p.pose.center_m),
                    Vec3::from(p.pose.approach),
                    Vec3::from(p.pose.closing),
                );
                let h = a.cross(&b) * (jaw.finger_height_m / 2.0);
                let half = p.pose.width_m / 2.0;
                let (f1, f2) = (centre - b * half, centre + b * half);
                seg(f1, f2, thick);
                for f in [f1, f2] {
                    seg(f - h, f + h, thick + 1);
                }
                // where the gripper comes from: a tilted approach shows as a tick off the centre
                seg(centre, centre - a * 0.03, thick);
            }
            (Grasp::Suction(s), Gripper::Suction(cup)) => {
                let (p, a) = (Vec3::from(s.pose.point_m), Vec3::from(s.pose.approach));
                let (e1, e2) = perpendiculars(&a);
                let ring = |i: usize| {
                    let t = std::f32::consts::TAU * i as f32 / 36.0;
                    p + (e1 * t.cos() + e2 * t.sin()) * cup.radius_m
                };
                for i in 0..36 {
                    seg(ring(i), ring(i + 1), thick);
                }
                seg(p, p - a * 0.03, thick);
            }
            _ => {}
        }
    }
    out
}

/// The gripper at each grasp as boxes, best first: a parallel jaw's two fingers and palm, a
/// suction cup's tool (a square prism of the cup's radius along the approach).
pub fn gripper_boxes(outcome: &PlanOutcome, gripper: &Gripper) -> Vec<BoxMesh> {
    let n = outcome.grasps.len();
    let mut boxes = Vec::new();
    for (rank, g) in outcome.grasps.iter().enumerate() {
        let colour = rank_colour(rank, n);
        let mut push = |centre: Vec3, axes: [Vec3; 3], half_m: [f32; 3]| {
            boxes.push(BoxMesh {
                centre_m: arr(centre),
                axes: axes.map(arr),
                half_m,
                colour,
            });
        };
        match (g, gripper) {
            (Grasp::Parallel(p), Gripper::Parallel(jaw)) => {
                let (c, a, b) = (
                    Vec3::from(p.pose.center_m),
                    Vec3::from(p.pose.approach),
                    Vec3::from(p.pose.closing),
                );
                let h = a.cross(&b);
                let (tip, len, palm) =
                    (jaw.contact_to_tip_m, jaw.finger_length_m, jaw.palm_depth_m);
                let half_w = p.pose.width_m / 2.0;
                let t = jaw.finger_thickness_m;
                let fx = tip - len / 2.0;
                for s in [-1.0f32, 1.0] {
                    push(
                        c + a * fx + b * (s * (half_w + t / 2.0)),
                        [a, b, h],
                        [len / 2.0, t / 2.0, jaw.finger_height_m / 2.0],
                    );
                }
                push(
                    c + a * (tip - len - palm / 2.0),
                    [a, b, h],
                    [palm / 2.0, half_w + t, jaw.finger_height_m / 2.0],
                );
            }
            (Grasp::Suction(s), Gripper::Suction(cup)) => {
                let (p, a) = (Vec3::from(s.pose.point_m), Vec3::from(s.pose.approach));
                let (e1, e2) = perpendiculars(&a);
                push(
                    p - a * (cup.tool_length_m / 2.0),
                    [a, e1, e2],
                    [cup.tool_length_m / 2.0, cup.radius_m, cup.radius_m],
                );
            }
            _ => {}
        }
    }
    boxes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grasp::{ParallelGrasp, ParallelPose, SuctionGrasp, SuctionPose};
    use crate::gripper::{ParallelJaw, SuctionCup};

    fn outcome(grasps: Vec<Grasp>) -> PlanOutcome {
        PlanOutcome {
            grasps,
            no_grasp_reason: None,
            candidates: 0,
        }
    }

    fn close(a: [f32; 3], b: [f32; 3]) -> bool {
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6)
    }

    #[test]
    fn a_parallel_grasp_shows_its_fingers_and_palm_where_the_pose_says() {
        // Top-down grasp at 0.5 m closing along x, 40 mm open: the fingers stand across the
        // closing line along y = approach × closing.
        let jaw = ParallelJaw::default();
        let pose = ParallelPose {
            center_m: [0.0, 0.0, 0.5],
            approach: [0.0, 0.0, 1.0],
            closing: [1.0, 0.0, 0.0],
            width_m: 0.04,
        };
        let o = outcome(vec![Grasp::Parallel(ParallelGrasp {
            success_prob: None,
            score: 0.9,
            pose,
            base: None,
        })]);
        let g = Gripper::Parallel(jaw);
        let segs = overlay_segments(&o, &g);
        assert_eq!(segs.len(), 4);
        assert!(close(segs[0].a_m, [-0.02, 0.0, 0.5]) && close(segs[0].b_m, [0.02, 0.0, 0.5]));
        let hh = jaw.finger_height_m / 2.0;
        assert!(close(segs[1].a_m, [-0.02, -hh, 0.5]) && close(segs[1].b_m, [-0.02, hh, 0.5]));
        assert_eq!(segs[1].half_width_px, 2, "the best grasp is drawn thicker");
        // the approach axis, 30 mm back towards the camera (top-down: a point in the image)
        assert!(close(segs[3].a_m, [0.0, 0.0, 0.5]) && close(segs[3].b_m, [0.0, 0.0, 0.47]));
        let boxes = gripper_boxes(&o, &g);
        assert_eq!(boxes.len(), 3);
        let t = jaw.finger_thickness_m;
        let along = 0.5 + jaw.contact_to_tip_m - jaw.finger_length_m / 2.0;
        assert!(close(boxes[0].centre_m, [-(0.02 + t / 2.0), 0.0, along]));
        assert!(close(boxes[1].centre_m, [0.02 + t / 2.0, 0.0, along]));
        let palm = 0.5 + jaw.contact_to_tip_m - jaw.finger_length_m - jaw.palm_depth_m / 2.0;
        assert!(close(boxes[2].centre_m, [0.0, 0.0, palm]));
        assert_eq!(boxes[2].half_m[1], 0.02 + t);
        // A suction grasp with a parallel gripper draws nothing.
        assert!(overlay_segments(&o, &Gripper::Suction(SuctionCup::default())).is_empty());
    }

    #[test]
    fn a_suction_grasp_shows_its_rim_around_the_approach() {
        let cup = SuctionCup::default();
        let o = outcome(vec![Grasp::Suction(SuctionGrasp {
            success_prob: None,
            score: 0.8,
            pose: SuctionPose {
                point_m: [0.1, -0.05, 0.6],
                approach: [0.0, 0.6, 0.8],
            },
            base: None,
        })]);
        let segs = overlay_segments(&o, &Gripper::Suction(cup));
        assert_eq!(segs.len(), 37);
        for s in &segs[..36] {
            let d = [s.a_m[0] - 0.1, s.a_m[1] + 0.05, s.a_m[2] - 0.6];
            let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            assert!((r - cup.radius_m).abs() < 1e-6, "rim radius {r}");
            assert!(
                (d[1] * 0.6 + d[2] * 0.8).abs() < 1e-6,
                "rim not across the approach"
            );
        }
        assert!(close(segs[36].b_m, [0.1, -0.05 - 0.018, 0.6 - 0.024]));
        let b = gripper_boxes(&o, &Gripper::Suction(cup));
        let l = cup.tool_length_m / 2.0;
        assert!(close(b[0].centre_m, [0.1, -0.05 - 0.6 * l, 0.6 - 0.8 * l]));
    }

    #[test]
    fn rank_colours_go_from_green_to_red() {
        assert_eq!(rank_colour(0, 5), [0, 230, 0]);
        assert_eq!(rank_colour(1, 5), [255, 220, 0]);
        assert_eq!(rank_colour(4, 5), [255, 0, 0]);
        assert_eq!(rank_colour(1, 2), [255, 220, 0]);
    }
}

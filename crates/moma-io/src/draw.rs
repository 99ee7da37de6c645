//! Drawing shapes on images: segments in the camera frame, projected with the intrinsics
//! (grasp overlays; the shapes come from `moma-grasp`).

use image::{Rgb, RgbImage};
use moma_core::Intrinsics;
use moma_core::shapes::Segment3;

/// Sets pixel `(x, y)` when it lies inside the image.
fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

/// A straight stroke from `a` to `b` (pixels), `half_width` pixels either side; at most 4096
/// steps (a segment projected far outside the image does not hang).
fn line(img: &mut RgbImage, a: (f32, f32), b: (f32, f32), c: [u8; 3], half_width: i64) {
    let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).clamp(1, 4096);
    for i in 0..=n {
        let t = i as f32 / n as f32;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        for dy in -half_width..=half_width {
            for dx in -half_width..=half_width {
                put(img, x.round() as i64 + dx, y.round() as i64 + dy, c);
            }
        }
    }
}

/// [`draw_segments`] legible on any background (a colour-mapped depth uses the rank colours'
/// hues too): every segment first as a dark outline one pixel wider, then all of them in their
/// colours, each `extra_half_width_px` wider than it says (thicker strokes on large images).
pub fn draw_segments_outlined(
    img: &mut RgbImage,
    k: &Intrinsics,
    segments: &[Segment3],
    extra_half_width_px: i64,
) {
    const OUTLINE: [u8; 3] = [20, 20, 20];
    for pass in [true, false] {
        for s in segments {
            if let (Some(a), Some(b)) = (k.project(s.a_m), k.project(s.b_m)) {
                let w = s.half_width_px + extra_half_width_px;
                if pass {
                    line(img, a, b, OUTLINE, w + 1);
                } else {
                    line(img, a, b, s.colour, w);
                }
            }
        }
    }
}

/// Draws `segments` (camera frame, metres) on `img`, in order (later ones on top), each
/// projected with `k`; a segment with an endpoint behind the camera is skipped, pixels outside
/// the image are clipped.
pub fn draw_segments(img: &mut RgbImage, k: &Intrinsics, segments: &[Segment3]) {
    for s in segments {
        if let (Some(a), Some(b)) = (k.project(s.a_m), k.project(s.b_m)) {
            line(img, a, b, s.colour, s.half_width_px);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use moma_core::ImageSize;

    #[test]
    fn a_segment_lands_where_the_camera_projects_it() {
        let k = Intrinsics::nominal(ImageSize::new(40, 30));
        let mut img = RgbImage::new(40, 30);
        // A horizontal segment through the principal point at 1 m, 0.1 m long.
        let s = Segment3 {
            a_m: [-0.05, 0.0, 1.0],
            b_m: [0.05, 0.0, 1.0],
            colour: [9, 8, 7],
            half_width_px: 0,
        };
        draw_segments(&mut img, &k, &[s]);
        let (u0, v) = k.project(s.a_m).unwrap();
        let (u1, _) = k.project(s.b_m).unwrap();
        let row = v.round() as u32;
        for u in u0.round() as u32..=u1.round() as u32 {
            assert_eq!(img.get_pixel(u, row).0, [9, 8, 7], "pixel {u}");
        }
        let painted = img.pixels().filter(|p| p.0 != [0, 0, 0]).count();
        assert_eq!(painted as u32, u1.round() as u32 - u0.round() as u32 + 1);
        // Behind the camera: nothing; far outside: clipped, no panic.
        let mut img2 = RgbImage::new(40, 30);
        let behind = Segment3 {
            a_m: [0.0, 0.0, -1.0],
            ..s
        };
        let far = Segment3 {
            a_m: [-1e6, 0.0, 1.0],
            b_m: [1e6, 0.0, 1.0],
            ..s
        };
        draw_segments(&mut img2, &k, &[behind, far]);
        assert!(img2.pixels().filter(|p| p.0 != [0, 0, 0]).count() <= 40);
    }
}

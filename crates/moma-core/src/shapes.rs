//! Plain 3-D shapes to show with a result (grasp overlays and meshes): what to draw, in the camera
//! frame (metres, x right, y down, z forward). Made by `moma-grasp`, drawn and written by
//! `moma-io`; no image or file code here.

/// A segment to draw on an image after projection: endpoints in metres (camera frame), a colour
/// and a stroke half-width in pixels (0 = one pixel wide).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment3 {
    /// First endpoint, metres.
    pub a_m: [f32; 3],
    /// Second endpoint, metres.
    pub b_m: [f32; 3],
    /// RGB.
    pub colour: [u8; 3],
    /// Half-width of the stroke, pixels.
    pub half_width_px: i64,
}

/// An oriented box: centre (metres), three unit axes, half sizes along them (metres), colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxMesh {
    /// Centre, metres.
    pub centre_m: [f32; 3],
    /// Unit axes.
    pub axes: [[f32; 3]; 3],
    /// Half sizes along the axes, metres.
    pub half_m: [f32; 3],
    /// RGB.
    pub colour: [u8; 3],
}

/// The 12 triangles of a box over the corner indices of [`BoxMesh::corners`], wound
/// consistently (normals towards the centre by the right-hand rule; viewers show both sides).
pub const BOX_TRIANGLES: [[u32; 3]; 12] = {
    const QUADS: [[u32; 4]; 6] = [
        [0, 2, 6, 4],
        [1, 5, 7, 3],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 1, 3, 2],
        [4, 6, 7, 5],
    ];
    let mut t = [[0u32; 3]; 12];
    let mut i = 0;
    while i < 6 {
        let q = QUADS[i];
        t[2 * i] = [q[0], q[1], q[2]];
        t[2 * i + 1] = [q[0], q[2], q[3]];
        i += 1;
    }
    t
};

impl BoxMesh {
    /// The 8 corners: corner `i` is `centre + Σ_k s_k(i)·half_k·axis_k` with `s_k(i) = +1` when
    /// bit `k` of `i` is set, else −1 (summed in the order of the axes).
    pub fn corners(&self) -> [[f32; 3]; 8] {
        let mut out = [[0.0f32; 3]; 8];
        for (i, corner) in out.iter_mut().enumerate() {
            let s = |bit: usize| if i & bit != 0 { 1.0f32 } else { -1.0 };
            let scaled = |k: usize, sign: f32| {
                let f = sign * self.half_m[k];
                self.axes[k].map(|a| a * f)
            };
            let (d0, d1, d2) = (scaled(0, s(1)), scaled(1, s(2)), scaled(2, s(4)));
            for c in 0..3 {
                corner[c] = self.centre_m[c] + d0[c] + d1[c] + d2[c];
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_has_its_corners_and_outward_faces() {
        let b = BoxMesh {
            centre_m: [1.0, 2.0, 3.0],
            axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            half_m: [0.5, 0.25, 0.125],
            colour: [1, 2, 3],
        };
        let c = b.corners();
        assert_eq!(c[0], [0.5, 1.75, 2.875]);
        assert_eq!(c[7], [1.5, 2.25, 3.125]);
        assert_eq!(c[1], [1.5, 1.75, 2.875]);
        // Every triangle's normal points the same way (towards the centre); each corner used.
        for t in BOX_TRIANGLES {
            let [p, q, r] = t.map(|i| c[i as usize]);
            let u = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            let v = [r[0] - p[0], r[1] - p[1], r[2] - p[2]];
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let m = [
                (p[0] + q[0] + r[0]) / 3.0 - 1.0,
                (p[1] + q[1] + r[1]) / 3.0 - 2.0,
                (p[2] + q[2] + r[2]) / 3.0 - 3.0,
            ];
            assert!(n[0] * m[0] + n[1] * m[1] + n[2] * m[2] < 0.0, "{t:?}");
        }
        let mut used = [false; 8];
        BOX_TRIANGLES
            .iter()
            .flatten()
            .for_each(|&i| used[i as usize] = true);
        assert!(used.iter().all(|&u| u));
    }
}

//! Small image-processing helpers for the simulator and the demo: nearest-valid hole filling and
//! Gaussian blur. Maps are `(height, width)` `f32` arrays; pixel `(u, v)` is `[[v, u]]`.

use ndarray::Array2;

/// Replaces every pixel where `valid` is false by the value of the nearest valid pixel
/// (exact Euclidean distance, Felzenszwalb–Huttenlocher lower envelope with arg-min tracking;
/// ties resolved towards the smaller index). Returns `None` when no pixel is valid.
pub fn fill_nearest(values: &Array2<f32>, valid: &Array2<bool>) -> Option<Array2<f32>> {
    let (h, w) = values.dim();
    if !valid.iter().any(|&b| b) {
        return None;
    }
    const INF: i64 = i64::MAX / 4;
    // Pass 1: per column, the nearest valid row (distance along the column).
    let mut src_row = Array2::<i64>::from_elem((h, w), -1);
    let mut dist = Array2::<i64>::from_elem((h, w), INF);
    for u in 0..w {
        let mut last: i64 = -1;
        for v in 0..h {
            if valid[[v, u]] {
                last = v as i64;
            }
            if last >= 0 {
                src_row[[v, u]] = last;
                dist[[v, u]] = v as i64 - last;
            }
        }
        let mut next: i64 = -1;
        for v in (0..h).rev() {
            if valid[[v, u]] {
                next = v as i64;
            }
            if next >= 0 && (src_row[[v, u]] < 0 || next - (v as i64) < dist[[v, u]]) {
                src_row[[v, u]] = next;
                dist[[v, u]] = next - v as i64;
            }
        }
    }
    // Pass 2: per row, lower envelope of parabolas (x − q)² + f(q) over columns q with finite f.
    let mut out = values.clone();
    let mut hull_q: Vec<usize> = Vec::with_capacity(w);
    let mut hull_z: Vec<f64> = Vec::with_capacity(w + 1);
    for v in 0..h {
        hull_q.clear();
        hull_z.clear();
        let f = |q: usize| -> f64 {
            let d = dist[[v, q]];
            (d * d) as f64
        };
        for q in 0..w {
            if dist[[v, q]] >= INF {
                continue;
            }
            loop {
                match hull_q.last() {
                    None => {
                        hull_q.push(q);
                        hull_z.push(f64::NEG_INFINITY);
                        break;
                    }
                    Some(&p) => {
                        let s = ((f(q) + (q * q) as f64) - (f(p) + (p * p) as f64))
                            / (2.0 * (q as f64 - p as f64));
                        if s <= hull_z[hull_z.len() - 1] {
                            hull_q.pop();
                            hull_z.pop();
                        } else {
                            hull_q.push(q);
                            hull_z.push(s);
                            break;
                        }
                    }
                }
            }
        }
        if hull_q.is_empty() {
            continue; // unreachable when any pixel is valid
        }
        let mut k = 0;
        for x in 0..w {
            while k + 1 < hull_q.len() && hull_z[k + 1] < x as f64 {
                k += 1;
            }
            let q = hull_q[k];
            let r = src_row[[v, q]] as usize;
            out[[v, x]] = values[[r, q]];
        }
    }
    Some(out)
}

/// Gaussian blur with standard deviation `sigma_px` (pixels), borders replicated.
/// Exact separable kernel (radius ⌈3σ⌉) for σ ≤ 3; for larger σ three successive box filters
/// whose combined variance matches σ² (Kovesi's "boxes for Gauss"), O(1) per pixel.
/// `sigma_px <= 0` returns a copy.
pub fn gaussian_blur(a: &Array2<f32>, sigma_px: f64) -> Array2<f32> {
    if sigma_px <= 0.0 {
        return a.clone();
    }
    let mut out = a.clone();
    let (h, w) = a.dim();
    let mut line = Vec::new();
    let mut tmp = Vec::new();
    let mut apply = |out: &mut Array2<f32>, along_rows: bool| {
        let (n_lines, len) = if along_rows { (h, w) } else { (w, h) };
        for l in 0..n_lines {
            line.clear();
            for i in 0..len {
                line.push(if along_rows { out[[l, i]] } else { out[[i, l]] } as f64);
            }
            filter_line(&mut line, &mut tmp, sigma_px);
            for (i, &x) in line.iter().enumerate() {
                if along_rows {
                    out[[l, i]] = x as f32;
                } else {
                    out[[i, l]] = x as f32;
                }
            }
        }
    };
    apply(&mut out, true);
    apply(&mut out, false);
    out
}

fn filter_line(line: &mut [f64], tmp: &mut Vec<f64>, sigma: f64) {
    let n = line.len() as i64;
    if n == 0 {
        return;
    }
    let at = |i: i64| -> usize { i.clamp(0, n - 1) as usize };
    tmp.clear();
    tmp.extend_from_slice(line);
    if sigma <= 3.0 {
        let r = (3.0 * sigma).ceil() as i64;
        let k: Vec<f64> = (-r..=r)
            .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp())
            .collect();
        let sum: f64 = k.iter().sum();
        for i in 0..n {
            let mut acc = 0.0;
            for (j, kw) in k.iter().enumerate() {
                acc += kw * tmp[at(i + j as i64 - r)];
            }
            line[i as usize] = acc / sum;
        }
        return;
    }
    // boxes for Gauss, 3 passes
    let passes = 3.0;
    let w_ideal = (12.0 * sigma * sigma / passes + 1.0).sqrt();
    let mut wl = w_ideal.floor() as i64;
    if wl % 2 == 0 {
        wl -= 1;
    }
    let wu = wl + 2;
    let m = ((12.0 * sigma * sigma
        - passes * (wl * wl) as f64
        - 4.0 * passes * wl as f64
        - 3.0 * passes)
        / (-4.0 * wl as f64 - 4.0))
        .round() as i64;
    for p in 0..3 {
        let width = if p < m { wl } else { wu };
        let r = (width - 1) / 2;
        tmp.clear();
        tmp.extend_from_slice(line);
        let mut acc: f64 = (-r..=r).map(|j| tmp[at(j)]).sum();
        let norm = 1.0 / (2 * r + 1) as f64;
        for i in 0..n {
            line[i as usize] = acc * norm;
            acc += tmp[at(i + r + 1)] - tmp[at(i - r)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_nearest_matches_brute_force() {
        let (h, w) = (23, 31);
        let mut vals = Array2::<f32>::zeros((h, w));
        let mut valid = Array2::from_elem((h, w), false);
        let pts = [(3, 4), (20, 2), (11, 29), (15, 15), (0, 30)];
        for (k, &(v, u)) in pts.iter().enumerate() {
            valid[[v, u]] = true;
            vals[[v, u]] = k as f32 + 1.0;
        }
        let out = fill_nearest(&vals, &valid).unwrap();
        for v in 0..h {
            for u in 0..w {
                let best = pts
                    .iter()
                    .map(|&(pv, pu)| (pv as i64 - v as i64).pow(2) + (pu as i64 - u as i64).pow(2))
                    .min()
                    .unwrap();
                let got = out[[v, u]] as usize - 1;
                let (pv, pu) = pts[got];
                let d = (pv as i64 - v as i64).pow(2) + (pu as i64 - u as i64).pow(2);
                assert_eq!(d, best, "pixel ({u},{v})");
            }
        }
        assert!(fill_nearest(&vals, &Array2::from_elem((h, w), false)).is_none());
    }

    #[test]
    fn blur_preserves_constants_and_mean_of_impulse() {
        let a = Array2::<f32>::from_elem((40, 50), 2.5);
        for s in [0.7, 2.0, 8.0] {
            let b = gaussian_blur(&a, s);
            assert!(b.iter().all(|&x| (x - 2.5).abs() < 1e-5));
        }
        let mut imp = Array2::<f32>::zeros((101, 101));
        imp[[50, 50]] = 1.0;
        for s in [1.5, 6.0] {
            let b = gaussian_blur(&imp, s);
            let sum: f32 = b.iter().sum();
            assert!((sum - 1.0).abs() < 1e-4);
            // variance along a row ≈ σ²
            let row = b.row(50);
            let tot: f64 = row.iter().map(|&x| x as f64).sum();
            let var: f64 = row
                .iter()
                .enumerate()
                .map(|(i, &x)| x as f64 * (i as f64 - 50.0).powi(2))
                .sum::<f64>()
                / tot;
            assert!(
                (var.sqrt() - s).abs() / s < 0.05,
                "σ {s} got {}",
                var.sqrt()
            );
        }
    }
}

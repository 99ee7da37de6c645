//! Pre/post-processing against the official Depth Anything V2 reference data
//! (`shared/reference/dav2`): own `preprocess(input.png)` vs `NAME.input.npy`, and
//! `resize_bilinear_align_corners(output_net)` vs `output_full`.

mod common;

use common::{
    MODELS, reference_dir, reference_image, reference_input, reference_json, reference_output,
};
use moma_depth::preprocess::{preprocess, resize_bilinear_align_corners};

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn preprocess_matches_reference_inputs() {
    let dir = reference_dir();
    let rgb = reference_image(&dir);
    for name in MODELS {
        let input_size = reference_json(&dir, name)["input_size"].as_u64().unwrap() as usize;
        let want = reference_input(&dir, name);
        let got = preprocess(&rgb, input_size).unwrap();
        assert_eq!(got.shape(), want.shape(), "{name}");
        let err = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        let mean = got
            .iter()
            .zip(&want)
            .map(|(a, b)| f64::from((a - b).abs()))
            .sum::<f64>()
            / got.len() as f64;
        eprintln!("{name}: preprocess vs input.npy: max abs err {err:.3e}, mean {mean:.3e}");
        // OpenCV INTER_CUBIC reproduced exactly up to summation order: ~1e-6 on normalised values.
        assert!(err < 1e-4, "{name}: max abs err {err}");
    }
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn postprocess_matches_reference_full_outputs() {
    let dir = reference_dir();
    for name in MODELS {
        let net = reference_output(&dir, name, "net");
        let want = reference_output(&dir, name, "full");
        let (h, w) = want.dim();
        let got = resize_bilinear_align_corners(&net.view(), h, w);
        let (err, range) = common::max_abs_err(&got, &want);
        eprintln!(
            "{name}: bilinear(output_net) vs output_full: max abs err {err:.3e} (range {range:.3})"
        );
        assert!(err <= 1e-5 * range.max(1.0), "{name}: {err}");
    }
}

//! Test support shared by the training ops' unit tests.

use candle_core::{Device, Tensor, Var};

/// Which entries a finite-difference check visits and how close it must be.
pub(crate) struct FdCheck {
    /// Every `stride`-th entry of the input.
    pub stride: usize,
    /// Floor of the relative error's denominator (entries whose gradient is near zero).
    pub floor: f64,
    /// Largest relative error `|fd − g| / max(|fd|, |g|, floor)`.
    pub tol: f64,
}

impl FdCheck {
    /// Every entry, relative error below 1e-6 (denominator floor 1e-8): the small ops' check.
    pub const EVERY_ENTRY: Self = Self {
        stride: 1,
        floor: 1e-8,
        tol: 1e-6,
    };
}

/// The input gradient of `Σ op(x) ⊙ r` at `x0` (f64, shape `shape`) by autograd, checked
/// against central finite differences (step 1e-6) as `check` says, else a panic naming `what`
/// and the entry. Returns the autograd gradient (row-major) for further checks.
pub(crate) fn check_input_gradient(
    what: &str,
    op: impl Fn(&Tensor) -> Tensor,
    x0: &[f64],
    shape: &[usize],
    r: &Tensor,
    check: FdCheck,
) -> Vec<f64> {
    let FdCheck { stride, floor, tol } = check;
    let f = |v: &[f64]| -> f64 {
        let x = Tensor::from_slice(v, shape, &Device::Cpu).unwrap();
        (op(&x) * r)
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    };
    let g = input_gradient(&op, x0, shape, r);
    let eps = 1e-6;
    for i in (0..x0.len()).step_by(stride) {
        let (mut p, mut m) = (x0.to_vec(), x0.to_vec());
        p[i] += eps;
        m[i] -= eps;
        let fd = (f(&p) - f(&m)) / (2.0 * eps);
        let rel = (fd - g[i]).abs() / fd.abs().max(g[i].abs()).max(floor);
        assert!(
            rel < tol,
            "{what} x[{i}]: autograd {} vs finite difference {fd} (rel {rel:.2e})",
            g[i]
        );
    }
    g
}

/// The input gradient of `Σ op(x) ⊙ r` at `x0` (f64, shape `shape`) by autograd, row-major.
pub(crate) fn input_gradient(
    op: impl Fn(&Tensor) -> Tensor,
    x0: &[f64],
    shape: &[usize],
    r: &Tensor,
) -> Vec<f64> {
    let x = Var::from_tensor(&Tensor::from_slice(x0, shape, &Device::Cpu).unwrap()).unwrap();
    (op(x.as_tensor()) * r)
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap()
        .get(x.as_tensor())
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// `max |a − b|` of two f64 tensors of one shape.
pub(crate) fn max_abs_diff(a: &Tensor, b: &Tensor) -> f64 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f64>()
        .unwrap()
}

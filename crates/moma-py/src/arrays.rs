//! NumPy arrays in: checked, and converted at most once.
//!
//! A C-contiguous `float32` array is read in place (no conversion); any other real dtype or
//! memory layout is converted once with `numpy.asarray(x, dtype=float32)`. Wrong number of
//! dimensions, a non-numeric dtype or an object that is not array-like raise
//! `moma.InvalidInputError` naming the argument.

use moma_core::Mask;
use ndarray::Array2;
use numpy::{
    PyArray2, PyArray3, PyArrayDescrMethods, PyArrayMethods, PyReadonlyArray2, PyReadonlyArray3,
    PyReadwriteArray2, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use crate::errors::value_err;

/// `numpy.asarray(obj)`, with a clear error when `obj` is not array-like.
fn as_ndarray<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<Bound<'py, PyUntypedArray>> {
    let np = obj.py().import("numpy")?;
    let arr = np
        .call_method1("asarray", (obj,))
        .map_err(|e| value_err(format!("{what}: not convertible to a NumPy array: {e}")))?;
    arr.cast_into::<PyUntypedArray>()
        .map_err(|_| value_err(format!("{what}: not convertible to a NumPy array")))
}

fn check_ndim(
    arr: &Bound<'_, PyUntypedArray>,
    ndim: usize,
    what: &str,
    layout: &str,
) -> PyResult<()> {
    if arr.ndim() != ndim {
        return Err(value_err(format!(
            "{what} must be a {ndim}-D array ({layout}), got shape {:?}",
            arr.shape()
        )));
    }
    Ok(())
}

/// The NumPy dtype kind character (`f`, `i`, `u`, `b`, `c`, `O`, `U`, …).
fn dtype_kind(arr: &Bound<'_, PyUntypedArray>) -> PyResult<char> {
    Ok(arr.dtype().kind() as char)
}

/// A 2-D `float32` array: `obj` itself when it already is one (any strides), else converted once
/// from a real (float/int/bool) 2-D array.
///
/// # Errors
/// `moma.InvalidInputError`: not array-like, not 2-D, or not of a real dtype.
pub fn f32_2d<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<PyReadonlyArray2<'py, f32>> {
    if let Ok(a) = obj.cast::<PyArray2<f32>>() {
        return a
            .try_readonly()
            .map_err(|e| value_err(format!("{what}: {e}")));
    }
    let mut arr = as_ndarray(obj, what)?;
    // a model's (1, H, W) or a file's (H, W, 1) is one map, as `moma.read_prediction` and the
    // CLI take it: its single axis dropped (a view, no copy)
    if arr.ndim() == 3 {
        let shape = arr.shape().to_vec();
        let axis = if shape[0] == 1 && shape[2] != 1 {
            Some(0)
        } else if shape[2] == 1 && shape[0] != 1 {
            Some(2)
        } else {
            None
        };
        if let Some(axis) = axis {
            let squeezed = obj
                .py()
                .import("numpy")?
                .call_method1("squeeze", (&arr, axis))?;
            // a float32 map read as it is, as a 2-D one would be
            if let Ok(a) = squeezed.cast::<PyArray2<f32>>() {
                return a
                    .try_readonly()
                    .map_err(|e| value_err(format!("{what}: {e}")));
            }
            arr = as_ndarray(&squeezed, what)?;
        }
    }
    check_ndim(&arr, 2, what, "height × width, or 1 × H × W, or H × W × 1")?;
    let kind = dtype_kind(&arr)?;
    if !matches!(kind, 'f' | 'i' | 'u' | 'b') {
        return Err(value_err(format!(
            "{what} has dtype {}, expected real numbers (float32 preferred)",
            arr.dtype()
        )));
    }
    let np = obj.py().import("numpy")?;
    let conv = np
        .call_method1("asarray", (&arr, "float32"))
        .map_err(|e| value_err(format!("{what}: cannot convert to float32: {e}")))?;
    // a finite float64 beyond float32's range becomes inf in the conversion: say so, rather
    // than let it be taken for the input's own NaN/inf
    if kind == 'f' {
        let overflowed = np.call_method1(
            "logical_and",
            (
                np.call_method1("isinf", (&conv,))?,
                np.call_method1("isfinite", (&arr,))?,
            ),
        )?;
        let count: usize = np.call_method1("count_nonzero", (overflowed,))?.extract()?;
        if count > 0 {
            return Err(value_err(format!(
                "{what} ({}) holds {count} value(s) beyond float32's range (|x| > 3.4e38), \
                 which moma computes in",
                arr.dtype()
            )));
        }
    }
    let conv = conv
        .cast_into::<PyArray2<f32>>()
        .map_err(|_| value_err(format!("{what}: cannot convert to a float32 2-D array")))?;
    conv.try_readonly()
        .map_err(|e| value_err(format!("{what}: {e}")))
}

/// A caller's output array `out`: a writable 2-D `float32` NumPy array (any strides), borrowed
/// mutably (written in place, never converted: a conversion would write into a copy).
///
/// # Errors
/// `moma.InvalidInputError`: not a 2-D float32 array, read-only, or already borrowed (e.g. the
/// same array passed as input and output).
pub fn f32_2d_out<'py>(out: &Bound<'py, PyAny>) -> PyResult<PyReadwriteArray2<'py, f32>> {
    let out = out.cast::<PyArray2<f32>>().map_err(|_| {
        value_err("out must be a writable 2-D float32 NumPy array (height × width)")
    })?;
    out.try_readwrite()
        .map_err(|e| value_err(format!("out: {e}")))
}

/// An `H × W × 3` `uint8` RGB array, borrowed from NumPy (any strides, not copied): read it with
/// `.as_array()`.
///
/// # Errors
/// `moma.InvalidInputError`: not 3-D with 3 channels, not `uint8`, or empty.
pub fn rgb_ro<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<PyReadonlyArray3<'py, u8>> {
    let ro: PyReadonlyArray3<'py, u8> = match obj.cast::<PyArray3<u8>>() {
        Ok(a) => a
            .try_readonly()
            .map_err(|e| value_err(format!("{what}: {e}")))?,
        Err(_) => {
            let arr = as_ndarray(obj, what)?;
            check_ndim(&arr, 3, what, "height × width × 3, uint8")?;
            return Err(value_err(format!(
                "{what} has dtype {}, expected uint8 (0–255 per channel)",
                arr.dtype()
            )));
        }
    };
    let (h, w, c) = ro.as_array().dim();
    if c != 3 {
        return Err(value_err(format!(
            "{what} must be height × width × 3 (RGB), got shape {:?}",
            ro.as_array().shape()
        )));
    }
    if h == 0 || w == 0 {
        return Err(value_err(format!(
            "{what} is empty (shape {:?})",
            ro.as_array().shape()
        )));
    }
    Ok(ro)
}

/// An `H × W × 3` `uint8` RGB image as an [`image::RgbImage`] (one copy into the image buffer).
///
/// # Errors
/// `moma.InvalidInputError`: not 3-D with 3 channels, or not `uint8`.
pub fn rgb_image(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<image::RgbImage> {
    let ro = rgb_ro(obj, what)?;
    let view = ro.as_array();
    let (h, w, _) = view.dim();
    let data: Vec<u8> = match view.as_slice() {
        Some(s) => s.to_vec(),
        None => view.iter().copied().collect(),
    };
    let (wu, hu) = (
        u32::try_from(w).map_err(|_| value_err(format!("{what}: too wide")))?,
        u32::try_from(h).map_err(|_| value_err(format!("{what}: too tall")))?,
    );
    image::RgbImage::from_raw(wu, hu, data)
        .ok_or_else(|| value_err(format!("{what}: buffer does not match its shape")))
}

/// A mask from a 2-D `bool` or `uint8` array (nonzero = inside).
///
/// # Errors
/// `moma.InvalidInputError`: not 2-D, or another dtype.
pub fn mask(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Mask> {
    let labels = labels(obj, what, false)?;
    Ok(Mask::new(labels.mapv(|l| l != 0)))
}

/// The objects to grasp from a 2-D `bool` array, or an integer array of labels (`uint8`,
/// `uint16`, `uint32`, `uint64`, `int8`, `int16`, `int32`, `int64`; nonzero = inside): an
/// instance label image keeps touching objects apart ([`Mask::from_labels`]), as `moma grasp
/// --mask` reads a label PNG.
///
/// # Errors
/// `moma.InvalidInputError`: not 2-D, another dtype, a negative label.
pub fn object_mask(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Mask> {
    Ok(Mask::from_labels(labels(obj, what, true)?.view()))
}

/// The values of a 2-D mask argument: `bool` and `uint8` always, the other integer types with
/// `integers` (a nested list as NumPy reads it).
fn labels(obj: &Bound<'_, PyAny>, what: &str, integers: bool) -> PyResult<ndarray::Array2<u64>> {
    if !obj.is_instance_of::<PyUntypedArray>() {
        return labels(as_ndarray(obj, what)?.as_any(), what, integers);
    }
    /// The values of an array of dtype `T`, or `None` for another dtype.
    fn of<T: numpy::Element + Copy>(
        obj: &Bound<'_, PyAny>,
        what: &str,
        to_label: impl Fn(T) -> Option<u64>,
    ) -> PyResult<Option<ndarray::Array2<u64>>> {
        let Ok(a) = obj.cast::<PyArray2<T>>() else {
            return Ok(None);
        };
        let ro = a
            .try_readonly()
            .map_err(|e| value_err(format!("{what}: {e}")))?;
        let mut bad = false;
        let l = ro.as_array().mapv(|v| {
            to_label(v).unwrap_or_else(|| {
                bad = true;
                0
            })
        });
        if bad {
            return Err(value_err(format!(
                "{what} holds a negative value: a mask is 0 outside, a positive label inside"
            )));
        }
        Ok(Some(l))
    }
    let u = |v: u64| Some(v);
    // one cast succeeds at most: only that dtype's values are converted
    let mut found = vec![
        of::<bool>(obj, what, |v| u(u64::from(v)))?,
        of::<u8>(obj, what, |v| u(u64::from(v)))?,
    ];
    if integers {
        found.extend([
            of::<u16>(obj, what, |v| u(u64::from(v)))?,
            of::<u32>(obj, what, |v| u(u64::from(v)))?,
            of::<u64>(obj, what, u)?,
            of::<i8>(obj, what, |v| u64::try_from(v).ok())?,
            of::<i16>(obj, what, |v| u64::try_from(v).ok())?,
            of::<i32>(obj, what, |v| u64::try_from(v).ok())?,
            of::<i64>(obj, what, |v| u64::try_from(v).ok())?,
        ]);
    }
    if let Some(l) = found.into_iter().flatten().next() {
        return Ok(l);
    }
    let arr = as_ndarray(obj, what)?;
    let expected = if integers {
        "bool or integer labels (uint8, uint16, uint32, uint64, int8, int16, int32, int64; \
         nonzero = inside)"
    } else {
        "bool or uint8 (nonzero = inside)"
    };
    check_ndim(&arr, 2, what, &format!("height × width, {expected}"))?;
    Err(value_err(format!(
        "{what} has dtype {}, expected {expected}",
        arr.dtype()
    )))
}

/// An optional mask argument.
///
/// # Errors
/// As [`mask`].
pub fn opt_mask(obj: Option<&Bound<'_, PyAny>>, what: &str) -> PyResult<Option<Mask>> {
    obj.filter(|o| !o.is_none())
        .map(|o| mask(o, what))
        .transpose()
}

/// An optional mask of objects to grasp.
///
/// # Errors
/// As [`object_mask`].
pub fn opt_object_mask(obj: Option<&Bound<'_, PyAny>>, what: &str) -> PyResult<Option<Mask>> {
    obj.filter(|o| !o.is_none())
        .map(|o| object_mask(o, what))
        .transpose()
}

/// Owned copy of a 2-D `float32` argument (for moma types that own their pixels).
///
/// # Errors
/// As [`f32_2d`].
pub fn f32_owned(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Array2<f32>> {
    Ok(f32_2d(obj, what)?.as_array().to_owned())
}

/// A 2-D depth map in metres ([`f32_2d`]), refused when it can only be millimetres: an integer
/// or bool dtype (a uint16 depth PNG holds millimetres), or a median over the valid pixels
/// (finite, > 0) above [`moma_core::MILLIMETRE_MEDIAN_M`], or one below
/// [`moma_core::NEAR_MEDIAN_M`] (metres divided by 1000 again).
///
/// # Errors
/// As [`f32_2d`]; the two cases above, naming the argument and what to do.
pub fn metres_2d<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<PyReadonlyArray2<'py, f32>> {
    let ro = if obj.is_instance_of::<PyArray2<f32>>() {
        f32_2d(obj, what)?
    } else {
        // read as NumPy reads it once, its dtype checked, then converted from that array
        let arr = as_ndarray(obj, what)?;
        if matches!(dtype_kind(&arr)?, 'i' | 'u' | 'b') {
            return Err(value_err(format!(
                "{what} has dtype {}: depth in metres is floating point (a uint16 depth PNG \
                 holds millimetres: divide by 1000, or read it with moma.read_depth)",
                arr.dtype()
            )));
        }
        f32_2d(arr.as_any(), what)?
    };
    match moma_core::unit_mistake(ro.as_array()) {
        None => Ok(ro),
        Some(moma_core::UnitMistake::Millimetres(median)) => Err(value_err(format!(
            "{what} has a median depth of {median} m: it looks like millimetres (depth \
             arguments are metres: divide by 1000)"
        ))),
        Some(moma_core::UnitMistake::TooNear(median)) => Err(value_err(format!(
            "{what} has a median depth of {:.1} mm: no scene a camera grasps in is that near \
             (depth arguments are metres: divided by 1000 once too often? a σ map is no depth)",
            f64::from(median) * 1000.0
        ))),
    }
}

/// [`metres_2d`], copied into an owned array.
pub fn metres_owned(obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Array2<f32>> {
    Ok(metres_2d(obj, what)?.as_array().to_owned())
}

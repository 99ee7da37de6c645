//! moma's error enums → the Python exception classes of `moma/_errors.py`.
//!
//! | Rust | Python |
//! |---|---|
//! | [`CoreError`] (bad arrays, parameters, degenerate fits), `moma_grasp::GraspError` and array checks of this crate | `moma.InvalidInputError` (`MomaError`, `ValueError`) |
//! | [`IoError`] (every file problem: missing, unreadable, malformed) | `moma.MomaFileError` (`MomaError`, `OSError`) |
//! | [`DepthError`]: `Shape` → invalid input, `Weights` → file, `Backend`/`Unavailable` | `moma.BackendError` (`MomaError`, `RuntimeError`) |
//! | `moma_train::TrainError`: bad options or data → invalid input, files → file, a failed step (non-finite loss) → backend | as the row of its kind |
//!
//! The Python message is moma's own `Display` text, which already names the file and the problem.

use moma_core::CoreError;
use moma_depth::DepthError;
use moma_io::IoError;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyType;

/// The Python exception classes moma raises.
#[derive(Debug, Clone, Copy)]
pub enum Kind {
    /// `moma.InvalidInputError` (also a `ValueError`).
    Value,
    /// `moma.MomaFileError` (also an `OSError`).
    File,
    /// `moma.BackendError` (also a `RuntimeError`).
    Backend,
}

static VALUE: PyOnceLock<Py<PyType>> = PyOnceLock::new();
static FILE: PyOnceLock<Py<PyType>> = PyOnceLock::new();
static BACKEND: PyOnceLock<Py<PyType>> = PyOnceLock::new();

fn class(py: Python<'_>, kind: Kind) -> PyResult<&Bound<'_, PyType>> {
    let (cell, name) = match kind {
        Kind::Value => (&VALUE, "InvalidInputError"),
        Kind::File => (&FILE, "MomaFileError"),
        Kind::Backend => (&BACKEND, "BackendError"),
    };
    cell.import(py, "moma._errors", name)
}

/// A Python exception of `kind` carrying `message`.
pub fn err(kind: Kind, message: impl Into<String>) -> PyErr {
    let message = message.into();
    Python::attach(|py| match class(py, kind) {
        Ok(cls) => PyErr::from_type(cls.clone(), message),
        // The package's error module is missing (the extension imported on its own): fall back
        // to the builtin class of the same meaning rather than losing the message.
        Err(_) => match kind {
            Kind::Value => pyo3::exceptions::PyValueError::new_err(message),
            Kind::File => pyo3::exceptions::PyOSError::new_err(message),
            Kind::Backend => pyo3::exceptions::PyRuntimeError::new_err(message),
        },
    })
}

/// `moma.InvalidInputError(message)`.
pub fn value_err(message: impl Into<String>) -> PyErr {
    err(Kind::Value, message)
}

/// The integer argument `name` as the unsigned type `T`. Taken as `T` directly, pyo3 turns a
/// negative value into a bare `OverflowError` that names neither the argument nor the rule
/// (and `except ValueError` misses it); this is an `InvalidInputError` naming both.
pub fn unsigned<T: TryFrom<i128>>(name: &str, value: i128) -> PyResult<T> {
    T::try_from(value).map_err(|_| {
        value_err(if value < 0 {
            format!("{name}={value}: must be a non-negative integer")
        } else {
            format!("{name}={value}: too large")
        })
    })
}

/// Conversion of moma's error enums into Python exceptions.
pub trait IntoPyErr {
    /// The Python exception for this error, with moma's message.
    fn into_py_err(self) -> PyErr;
}

impl IntoPyErr for CoreError {
    fn into_py_err(self) -> PyErr {
        err(Kind::Value, self.to_string())
    }
}

impl IntoPyErr for IoError {
    fn into_py_err(self) -> PyErr {
        err(Kind::File, chain(&self))
    }
}

impl IntoPyErr for moma_grasp::GraspError {
    fn into_py_err(self) -> PyErr {
        err(Kind::Value, chain(&self))
    }
}

impl IntoPyErr for DepthError {
    fn into_py_err(self) -> PyErr {
        let kind = match &self {
            DepthError::Shape(_) => Kind::Value,
            DepthError::Weights { .. } | DepthError::Config { .. } => Kind::File,
            _ => Kind::Backend,
        };
        err(kind, chain(&self))
    }
}

impl IntoPyErr for moma_train::TrainError {
    fn into_py_err(self) -> PyErr {
        use moma_train::TrainError;
        match self {
            TrainError::Invalid(m) | TrainError::Data(m) => err(Kind::Value, m),
            TrainError::Io(e) => e.into_py_err(),
            TrainError::Depth(e) => (*e).into_py_err(),
            e @ (TrainError::Training { .. } | TrainError::Interrupted { .. }) => {
                err(Kind::Backend, chain(&e))
            }
        }
    }
}

/// The error and its sources joined by ": " (each library error prints only its own part).
fn chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(": ");
        text.push_str(&s.to_string());
        source = s.source();
    }
    text
}

/// `result.map_err(IntoPyErr::into_py_err)`, shorter.
pub trait ResultExt<T> {
    /// Maps the error into its Python exception.
    fn py(self) -> PyResult<T>;
}

impl<T, E: IntoPyErr> ResultExt<T> for Result<T, E> {
    fn py(self) -> PyResult<T> {
        self.map_err(IntoPyErr::into_py_err)
    }
}

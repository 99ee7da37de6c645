//! Helpers shared by the `FromStr` / `Display` implementations of moma's named settings
//! ([`crate::align::Method`], [`crate::normalise::Normalisation`],
//! [`crate::normalise::AlignSpace`], [`crate::sampling::SamplingStrategy`],
//! [`crate::PredictionKind`]). Each name is defined once, next to its type; the CLI, the
//! evaluation and the file formats derive from those definitions.

/// `a, b, c` for an error message listing the accepted names.
pub(crate) fn join<'a>(names: impl IntoIterator<Item = &'a str>) -> String {
    names.into_iter().collect::<Vec<_>>().join(", ")
}

/// The value of `all` whose name is `s`, or an error listing the accepted names:
/// "unknown {what} '{s}' (expected one of: a, b, …)".
pub(crate) fn parse<T: Copy>(
    s: &str,
    all: &[T],
    name: fn(T) -> &'static str,
    what: &str,
) -> crate::Result<T> {
    all.iter().copied().find(|&v| name(v) == s).ok_or_else(|| {
        crate::CoreError::InvalidParameter(format!(
            "unknown {what} '{s}' (expected one of: {})",
            join(all.iter().map(|&v| name(v)))
        ))
    })
}

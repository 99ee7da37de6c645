//! Helpers shared by the `FromStr` / `Display` implementations of moma's named settings
//! ([`crate::align::Method`], [`crate::normalise::Normalisation`],
//! [`crate::normalise::AlignSpace`], [`crate::sampling::SamplingStrategy`],
//! [`crate::PredictionKind`]). Each name is defined once, next to its type; the CLI, the
//! evaluation and the file formats derive from those definitions.

/// `a, b, c` for an error message listing the accepted names.
pub(crate) fn join<'a>(names: impl IntoIterator<Item = &'a str>) -> String {
    names.into_iter().collect::<Vec<_>>().join(", ")
}

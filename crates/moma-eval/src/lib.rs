//! moma-eval (work in progress)

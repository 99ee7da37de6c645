//! moma-io (work in progress)

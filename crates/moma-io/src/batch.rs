//! Order-preserving, bounded parallel processing of many frames (`moma align` over a folder):
//! decode, compute and encode run on the rayon pool, at most `in_flight` frames at a time, so
//! memory stays bounded however many frames there are, and results are handed on in input
//! order (reports and summaries do not depend on the thread count).

use rayon::prelude::*;

/// Frames in flight by default: two per rayon thread (one decoding or encoding while another
/// aligns), a few MB each at 640×480.
pub fn default_in_flight() -> usize {
    2 * rayon::current_num_threads().max(1)
}

/// Runs `work(i)` for `i` in `0..n` on the rayon pool, in batches of at most `in_flight`
/// indices (`0` counts as 1), and calls `done(i, value)` in increasing `i` after each batch.
/// At most `in_flight` results are held at once.
///
/// # Errors
/// The first error in index order, from `work` or `done`; the batch it occurs in has run to
/// its end (its other frames' files are written), later batches do not start.
///
/// # Example
/// ```
/// let mut seen = Vec::new();
/// moma_io::batch::map_bounded(
///     10,
///     3,
///     |i| Ok::<_, String>(i * i),
///     |i, sq| {
///         seen.push((i, sq));
///         Ok(())
///     },
/// )?;
/// assert_eq!(seen, (0..10).map(|i| (i, i * i)).collect::<Vec<_>>());
/// # Ok::<(), String>(())
/// ```
pub fn map_bounded<T, E>(
    n: usize,
    in_flight: usize,
    work: impl Fn(usize) -> Result<T, E> + Sync,
    mut done: impl FnMut(usize, T) -> Result<(), E>,
) -> Result<(), E>
where
    T: Send,
    E: Send,
{
    let batch = in_flight.max(1);
    let mut start = 0;
    while start < n {
        let end = (start + batch).min(n);
        let results: Vec<Result<T, E>> = (start..end).into_par_iter().map(&work).collect();
        for (i, r) in (start..end).zip(results) {
            done(i, r?)?;
        }
        start = end;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// Never more than `in_flight` frames are worked on at once, every index runs once, and the
    /// first error in index order is the one returned (later batches never start).
    #[test]
    fn bounded_ordered_and_stops_at_the_first_error() {
        let (running, peak, calls) = (
            AtomicUsize::new(0),
            AtomicUsize::new(0),
            AtomicUsize::new(0),
        );
        let mut order = Vec::new();
        map_bounded(
            50,
            4,
            |i| {
                let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                peak.fetch_max(now, Ordering::SeqCst);
                calls.fetch_add(1, Ordering::SeqCst);
                std::thread::sleep(std::time::Duration::from_micros(200));
                running.fetch_sub(1, Ordering::SeqCst);
                Ok::<_, String>(i)
            },
            |i, v| {
                assert_eq!(i, v);
                order.push(i);
                Ok(())
            },
        )
        .unwrap();
        assert_eq!(order, (0..50).collect::<Vec<_>>());
        assert!(peak.load(Ordering::SeqCst) <= 4);
        assert_eq!(calls.load(Ordering::SeqCst), 50);

        let calls = AtomicUsize::new(0);
        let e = map_bounded(
            20,
            5,
            |i| {
                calls.fetch_add(1, Ordering::SeqCst);
                if i == 7 || i == 8 {
                    Err(format!("frame {i}"))
                } else {
                    Ok(i)
                }
            },
            |_, _| Ok(()),
        )
        .unwrap_err();
        assert_eq!(e, "frame 7");
        assert_eq!(calls.load(Ordering::SeqCst), 10, "batches 0–4 and 5–9 only");
        let e = map_bounded(6, 0, Ok::<_, String>, |i, _| {
            if i == 2 {
                Err("done failed".to_string())
            } else {
                Ok(())
            }
        })
        .unwrap_err();
        assert_eq!(e, "done failed");
    }
}

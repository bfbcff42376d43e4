//! CPU-bound work off the async runtime, on the process's one fixed-size rayon pool (the pool the
//! in-process driver uses, sized by `--threads`).
//!
//! Not tokio's blocking pool: that one starts a thread per waiting call (up to 512) and lets
//! idle ones linger, and glibc gives every allocating thread its own malloc arena, each keeping
//! the high-water mark of the largest task it ran. On the small campaign the embedded runner's
//! peak RSS was 424 MB on the blocking pool against 181 MB in-process; on this pool it is
//! bounded by the pool's size like the in-process driver's.

use std::panic::{catch_unwind, AssertUnwindSafe};

/// Runs `work` on the rayon pool and waits for it without blocking the runtime. A panic in
/// `work` comes back as `Err` with its message instead of aborting the process.
pub(crate) async fn run<T: Send + 'static>(work: impl FnOnce() -> T + Send + 'static) -> Result<T, String> {
    let (done, result) = tokio::sync::oneshot::channel();
    rayon::spawn(move || {
        let outcome = catch_unwind(AssertUnwindSafe(work)).map_err(|panic| {
            panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a task panicked".to_string())
        });
        // The waiting task may have been dropped (cancelled); its result is not needed then.
        let _ = done.send(outcome);
    });
    result.await.map_err(|_| "the compute pool dropped a task".to_string())?
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn work_runs_on_the_fixed_pool_and_a_panic_is_an_error() {
        let pool_thread = run(rayon::current_thread_index).await.unwrap();
        assert!(pool_thread.is_some(), "the work ran outside the rayon pool");
        let sum = run(|| (1..=100u64).sum::<u64>()).await.unwrap();
        assert_eq!(sum, 5050);
        let e = run(|| -> u32 { panic!("chunk 7 is bad") }).await.unwrap_err();
        assert_eq!(e, "chunk 7 is bad");
        let tile = 3;
        let e = run(move || -> u32 { panic!("tile {tile} is bad") }).await.unwrap_err();
        assert_eq!(e, "tile 3 is bad");
        // The pool survives a panicking job.
        assert_eq!(run(|| 2 + 2).await.unwrap(), 4);
    }
}

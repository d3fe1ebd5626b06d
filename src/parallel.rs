//! The thread pool numerical work runs on, shared by every stage and plan of a given size:
//! stages that compute at once share its threads instead of each starting as many as there
//! are cores (which oversubscribed the machine when a NUFFT plan owned its own pool).

use crate::{Error, Result};
use rayon::ThreadPool;
use std::sync::{Arc, Mutex};

/// The pools made so far, by thread count: one per size asked for (in a run, one).
static POOLS: Mutex<Vec<(usize, Arc<ThreadPool>)>> = Mutex::new(Vec::new());

/// The shared pool of `threads` threads (0: one per core), started the first time it is
/// asked for.
///
/// One thread is the exception: work asking for one thread is work run many at a time (the
/// training-set samples), each confined to a thread of its own, so it gets a pool of its own
/// rather than all of it queueing on one shared thread.
pub fn shared_pool(threads: usize) -> Result<Arc<ThreadPool>> {
    let threads = if threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { threads };
    if threads == 1 {
        return start(1).map(Arc::new);
    }
    let mut pools = POOLS.lock().expect("no thread panics while holding the pool list");
    if let Some((_, pool)) = pools.iter().find(|(n, _)| *n == threads) {
        return Ok(pool.clone());
    }
    let pool = Arc::new(start(threads)?);
    pools.push((threads, pool.clone()));
    Ok(pool)
}

fn start(threads: usize) -> Result<ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("r2d2-compute-{i}"))
        .build()
        .map_err(|e| Error::OutOfMemory(format!("cannot start {threads} compute threads: {e} (is the address space limited? ulimit -v)")))
}

/// Starts the pool of `threads` threads now (the engine sizes it once, when it is made).
pub(crate) fn size_shared_pool(threads: usize) -> Result<()> {
    shared_pool(threads).map(drop)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_pool_per_size() {
        let a = shared_pool(2).unwrap();
        let b = shared_pool(2).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!(a.current_num_threads(), 2);
        assert!(!Arc::ptr_eq(&a, &shared_pool(3).unwrap()));
    }
}

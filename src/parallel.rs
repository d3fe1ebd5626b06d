//! The thread pool numerical work runs on, shared by every stage and plan of a given size:
//! stages that compute at once share its threads instead of each starting as many as there
//! are cores (which oversubscribed the machine when a NUFFT plan owned its own pool).

use crate::{Error, Result};
use rayon::ThreadPool;
use std::sync::{Arc, Mutex};

/// The pools made so far, by thread count: one per size asked for (in a run, one).
static POOLS: Mutex<Pools> = Mutex::new(Pools { process: 0, by_size: Vec::new() });

/// The pools, and the process whose compute threads the engine uses (0: none yet).
struct Pools {
    process: u32,
    by_size: Vec<(usize, Arc<ThreadPool>)>,
}

/// Records this process as the one whose compute threads the engine uses, or refuses a process
/// forked from that one. Fork copies only the thread that forks: the pools here, and rayon's
/// global pool (which parts of the engine use and which cannot be started again), would be
/// waited on for ever by a forked child (a Python `multiprocessing` worker under Linux's
/// default start method). Every entry to the engine calls it: an engine, a pool, an embedding
/// program's call.
pub fn claim_process() -> Result<()> {
    claim(&mut POOLS.lock().expect("no thread panics while holding the pool list"))
}

fn claim(pools: &mut Pools) -> Result<()> {
    let child = std::process::id();
    match pools.process {
        0 => pools.process = child,
        parent if parent != child => return Err(Error::Forked { parent, child }),
        _ => {}
    }
    Ok(())
}

/// The shared pool of `threads` threads (0: one per core), started the first time it is
/// asked for.
///
/// One thread is the exception: work asking for one thread is work run many at a time (the
/// training-set samples), each confined to a thread of its own, so it gets a pool of its own
/// rather than all of it queueing on one shared thread.
pub fn shared_pool(threads: usize) -> Result<Arc<ThreadPool>> {
    let threads = if threads == 0 { std::thread::available_parallelism().map_or(1, |n| n.get()) } else { threads };
    let mut pools = POOLS.lock().expect("no thread panics while holding the pool list");
    claim(&mut pools)?;
    if threads == 1 {
        drop(pools);
        return start(1).map(Arc::new);
    }
    if let Some((_, pool)) = pools.by_size.iter().find(|(n, _)| *n == threads) {
        return Ok(pool.clone());
    }
    let pool = Arc::new(start(threads)?);
    pools.by_size.push((threads, pool.clone()));
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
    use rayon::prelude::*;

    #[test]
    fn one_pool_per_size() {
        let a = shared_pool(2).unwrap();
        let b = shared_pool(2).unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert_eq!(a.current_num_threads(), 2);
        assert!(!Arc::ptr_eq(&a, &shared_pool(3).unwrap()));
    }

    /// A process forked after the engine's threads started (Python's `multiprocessing` does)
    /// has none of them: the engine refuses to run there, with what to do, instead of waiting
    /// for ever on them.
    #[cfg(unix)]
    #[test]
    fn a_process_forked_after_the_threads_started_is_refused_not_left_waiting() {
        use std::time::{Duration, Instant};
        let threads = 3;
        assert_eq!(shared_pool(threads).unwrap().install(|| (1..=100u64).into_par_iter().sum::<u64>()), 5050);
        let parent = std::process::id();
        // SAFETY: the child runs only the pool lookup, the error's formatting (glibc keeps its
        // heap usable across fork) and a write(2), then _exit(2)s without running this
        // process's exit code.
        let child = unsafe { libc::fork() };
        assert!(child >= 0, "fork: {}", std::io::Error::last_os_error());
        if child == 0 {
            let expected = format!("this process ({}) was forked from process {parent} after the engine had started its compute threads there", std::process::id());
            let refused = [shared_pool(threads).err(), shared_pool(1).err(), claim_process().err()]
                .iter()
                .all(|e| e.as_ref().is_some_and(|e| e.to_string().starts_with(&expected) && e.to_string().contains("multiprocessing.get_context(\"spawn\")")));
            unsafe { libc::_exit(if refused { 0 } else { 1 }) };
        }
        let began = Instant::now();
        let mut status = 0;
        // SAFETY (each waitpid and kill): our own child, which nothing else waits for.
        while unsafe { libc::waitpid(child, &mut status, libc::WNOHANG) } == 0 {
            if began.elapsed() > Duration::from_secs(30) {
                unsafe { libc::kill(child, libc::SIGKILL) };
                unsafe { libc::waitpid(child, &mut status, 0) };
                panic!("the forked process still waits after 30 s");
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        assert!(libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0, "the forked process was not refused as expected: status {status:#x}");
        // This process goes on.
        assert!(claim_process().is_ok());
    }
}

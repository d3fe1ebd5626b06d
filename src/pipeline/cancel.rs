//! Stopping a run. Each run owns a [`RunStop`]: the run's stages poll it, and it turns set
//! when a stage fails or when the caller's cancel flag turns true (the CLI's Ctrl-C, SIGTERM
//! and SIGHUP handler sets that flag; Python's sets its call's). It belongs to that run only:
//! a run that was stopped leaves nothing set for the next one in the same process, and the
//! runner never writes the caller's flag.
//!
//! Stopping also runs the hooks that parts of the run registered while it was being built or
//! run (a plugin host registers one that kills it, so that a hung plugin cannot keep the run
//! waiting). Those parts find their run through [`current`]: the runner marks the threads
//! that build and run its stages.

use std::cell::RefCell;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

type Hook = Box<dyn Fn() + Send>;

/// The stop state of one run (cheap to clone: clones share it).
#[derive(Clone, Default)]
pub(crate) struct RunStop {
    inner: Arc<Inner>,
}

#[derive(Default)]
struct Inner {
    stopped: AtomicBool,
    next_hook: AtomicU64,
    hooks: Mutex<Vec<(u64, Hook)>>,
}

impl RunStop {
    pub fn new() -> RunStop {
        RunStop::default()
    }

    pub fn is_stopped(&self) -> bool {
        self.inner.stopped.load(Ordering::SeqCst)
    }

    /// Stops the run: sets the state and runs every hook registered (once each).
    pub fn stop(&self) {
        if self.inner.stopped.swap(true, Ordering::SeqCst) {
            return;
        }
        let hooks = std::mem::take(&mut *self.inner.hooks.lock().unwrap_or_else(|e| e.into_inner()));
        for (_, hook) in hooks {
            hook();
        }
    }

    /// Runs `hook` when the run stops (at once if it has), unless the returned guard is dropped
    /// first.
    pub fn on_stop(&self, hook: impl Fn() + Send + 'static) -> HookGuard {
        let id = self.inner.next_hook.fetch_add(1, Ordering::SeqCst);
        self.inner.hooks.lock().unwrap_or_else(|e| e.into_inner()).push((id, Box::new(hook)));
        // A stop that came before the hook was in the list has not run it.
        if self.is_stopped() {
            let hooks = std::mem::take(&mut *self.inner.hooks.lock().unwrap_or_else(|e| e.into_inner()));
            for (_, hook) in hooks {
                hook();
            }
        }
        HookGuard { stop: self.clone(), id }
    }

    /// Marks this thread as working for this run until the guard is dropped.
    pub fn enter(&self) -> Entered {
        let previous = CURRENT.with(|c| c.replace(Some(self.clone())));
        Entered { previous }
    }
}

/// Unregisters its hook when dropped.
pub(crate) struct HookGuard {
    stop: RunStop,
    id: u64,
}

impl Drop for HookGuard {
    fn drop(&mut self) {
        self.stop.inner.hooks.lock().unwrap_or_else(|e| e.into_inner()).retain(|(id, _)| *id != self.id);
    }
}

thread_local! {
    static CURRENT: RefCell<Option<RunStop>> = const { RefCell::new(None) };
}

/// The run this thread builds or runs stages for, if any.
pub(crate) fn current() -> Option<RunStop> {
    CURRENT.with(|c| c.borrow().clone())
}

/// Restores the thread's previous run when dropped.
pub(crate) struct Entered {
    previous: Option<RunStop>,
}

impl Drop for Entered {
    fn drop(&mut self) {
        let previous = self.previous.take();
        CURRENT.with(|c| *c.borrow_mut() = previous);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    #[test]
    fn stopping_runs_the_registered_hooks_once_and_only_of_that_run() {
        let (a, b) = (RunStop::new(), RunStop::new());
        let calls = Arc::new(AtomicUsize::new(0));
        let count = |calls: &Arc<AtomicUsize>| {
            let calls = calls.clone();
            move || {
                calls.fetch_add(1, Ordering::SeqCst);
            }
        };
        let _on_a = a.on_stop(count(&calls));
        let dropped = a.on_stop(count(&calls));
        drop(dropped);
        let _on_b = b.on_stop(count(&calls));
        a.stop();
        a.stop();
        assert_eq!(calls.load(Ordering::SeqCst), 1);
        assert!(a.is_stopped() && !b.is_stopped());
        // Registered after the stop: run at once.
        let _late = a.on_stop(count(&calls));
        assert_eq!(calls.load(Ordering::SeqCst), 2);
    }

    #[test]
    fn a_thread_knows_its_run_while_entered() {
        assert!(current().is_none());
        let run = RunStop::new();
        {
            let _in = run.enter();
            current().expect("entered").stop();
        }
        assert!(current().is_none());
        assert!(run.is_stopped());
    }
}

//! Work a training step starts early and joins later (the rate term's own graph): on an
//! operating-system thread of its own, or as a job of rayon's pool when the step itself runs
//! on a worker of that pool.
//!
//! Why two forms. A CPU step runs its parallel regions (the CPU twin's tiles, the row gathers,
//! ndarray's matrix products) on rayon's pool; started from a thread outside the pool, each
//! region is handed to the pool while the caller sleeps on a latch (three threads on two cores,
//! a futex wake and wait per region: ~12 % of a step's samples in the kernel's scheduler,
//! docs/benchmarks.md "The step on the pool"). Run on a worker, the step splits its regions
//! with the other worker instead. But a worker must never block on something that needs the
//! pool: a worker waiting in `JoinHandle::join` on a thread whose own regions wait for a free
//! worker is how two trainings in one process deadlocked when the step first ran on the pool.
//! So on the pool the background work is a pool job, and its waiter keeps executing the pool's
//! jobs (rayon's `yield_now`) until it is done.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::{Arc, Mutex};
use std::thread::{JoinHandle, Thread};
use std::time::Duration;

/// Where [`Background::start`] runs its work.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StartOn {
    /// An operating-system thread of its own (the step runs outside rayon's pool).
    Thread,
    /// A job of rayon's pool (the step runs on one of its workers).
    Pool,
}

/// Work started by [`Background::start`], its result taken by [`Background::join`].
pub enum Background<T> {
    Thread(JoinHandle<T>),
    Pool(Arc<Mutex<PoolSlot<T>>>),
}

/// A pool job's result once it has one, and the thread waiting for it.
pub struct PoolSlot<T> {
    result: Option<std::thread::Result<T>>,
    waiter: Option<Thread>,
}

/// How long a waiter with no pool work at hand sleeps before it looks again (it is also woken
/// when the job ends). Short: jobs the background work splits off while the waiter sleeps are
/// left to the other workers until it wakes.
const IDLE_WAIT: Duration = Duration::from_micros(50);

impl<T: Send + 'static> Background<T> {
    pub fn start(on: StartOn, work: impl FnOnce() -> T + Send + 'static) -> Self {
        match on {
            StartOn::Thread => Background::Thread(std::thread::spawn(work)),
            StartOn::Pool => {
                let slot = Arc::new(Mutex::new(PoolSlot {
                    result: None,
                    waiter: None,
                }));
                let filled = slot.clone();
                rayon::spawn(move || {
                    // Caught here: a panic in a rayon::spawn job would abort the process; the
                    // waiter gets it as a thread's join would.
                    let result = catch_unwind(AssertUnwindSafe(work));
                    let waiter = {
                        let mut slot = filled.lock().unwrap_or_else(|e| e.into_inner());
                        slot.result = Some(result);
                        slot.waiter.take()
                    };
                    if let Some(thread) = waiter {
                        thread.unpark();
                    }
                });
                Background::Pool(slot)
            }
        }
    }

    /// The work's result, or its panic. On the pool the waiting thread executes other pool
    /// jobs meanwhile (the work itself, when no other worker has taken it yet).
    pub fn join(self) -> std::thread::Result<T> {
        match self {
            Background::Thread(thread) => thread.join(),
            Background::Pool(slot) => loop {
                {
                    let mut slot = slot.lock().unwrap_or_else(|e| e.into_inner());
                    if let Some(result) = slot.result.take() {
                        return result;
                    }
                    slot.waiter = Some(std::thread::current());
                }
                match rayon::yield_now() {
                    Some(rayon::Yield::Executed) => {}
                    // Nothing to help with (or not on a worker): sleep until the job ends or
                    // the next look.
                    Some(rayon::Yield::Idle) | None => std::thread::park_timeout(IDLE_WAIT),
                }
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn thread_and_pool_give_the_work_result() {
        for on in [StartOn::Thread, StartOn::Pool] {
            let job = Background::start(on, || (0..1000u64).sum::<u64>());
            assert_eq!(job.join().unwrap(), 499_500, "{on:?}");
        }
    }

    #[test]
    fn a_panic_comes_back_from_join() {
        for on in [StartOn::Thread, StartOn::Pool] {
            let job = Background::start(on, || -> u32 { panic!("background work failed") });
            assert!(job.join().is_err(), "{on:?}");
        }
    }

    /// Every worker of a two-worker pool joins background work at once (a barrier holds each
    /// until both are there), and that work's parallel regions run on the same pool: the case
    /// that deadlocked two trainings. `None` when the joins did not finish within `limit`.
    fn every_worker_joins(on: StartOn, limit: Duration) -> Option<Vec<u64>> {
        let pool = Arc::new(
            rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap(),
        );
        let (sender, receiver) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let both_waiting = std::sync::Barrier::new(2);
            let sums = pool.broadcast(|worker| {
                let i = worker.index() as u64;
                both_waiting.wait();
                let on_pool = pool.clone();
                let job = Background::start(on, move || {
                    on_pool.install(|| (0..200_000u64).into_par_iter().map(|x| x % (i + 2)).sum())
                });
                // Joined at once: between the barrier and the join a worker takes no pool work,
                // so with threads of their own both workers are surely blocked.
                job.join().unwrap()
            });
            let _ = sender.send(sums);
        });
        receiver.recv_timeout(limit).ok()
    }

    #[test]
    fn every_worker_waiting_on_pool_work_still_finishes() {
        let sums = every_worker_joins(StartOn::Pool, Duration::from_secs(120))
            .expect("the waiters did not finish: a worker blocked on work that needs the pool");
        for (i, sum) in sums.iter().enumerate() {
            let i = i as u64;
            let expected: u64 = (0..200_000u64).map(|x| x % (i + 2)).sum();
            assert_eq!(*sum, expected);
        }
    }

    /// The counter-check that the case above can fail: with the background work on threads of
    /// its own, the same joins never finish (both workers blocked, the threads' regions waiting
    /// for a free worker; the stuck threads are left behind, to end with the test process).
    #[test]
    fn os_threads_joined_by_every_worker_deadlock() {
        assert!(
            every_worker_joins(StartOn::Thread, Duration::from_secs(3)).is_none(),
            "the joins finished: the deadlock case no longer holds every worker"
        );
    }
}

//! The bounded pool that runs all CPU work of requests (OpenCV, ONNX Runtime, index search, fsync).
//!
//! Why: async worker threads must never block, and on a 2-core machine an unbounded queue only turns
//! overload into ever-growing latency and memory. The pool has a fixed number of threads and a fixed
//! number of waiting slots; a job that finds no slot is refused at once ([`PoolError::Full`], which the
//! transports answer with RESOURCE_EXHAUSTED / 429), and a job whose deadline passed while it waited is
//! dropped without running ([`PoolError::Expired`]), so a burst cannot leave a backlog of work nobody awaits.
//!
//! Admission: a job takes one of `threads + queue` slots, held until it has run (or was skipped). The
//! transports ask [`CpuPool::check_room`] before they read or decode a request body, so a client that keeps
//! sending while every slot is taken is refused for the price of a request head, not of its body: without
//! that, a storm of clients that do not back off spent the server's core on receiving and refusing bodies.
//! The check reserves nothing. A body can take as long as the client likes to arrive, and a slot held
//! meanwhile would idle the CPU and refuse everybody else (ten slow uploads would shut the service); so the
//! slot is taken when the job is submitted, and the few requests that pass the check in the instant before a
//! slot is taken are refused then, after their body.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Instant;

use parking_lot::Mutex;

type Job = Box<dyn FnOnce() + Send + 'static>;

/// Cores this process may run on (its CPU affinity: a server pinned to one core sees 1), read once. The
/// stages that split one request's work over two threads (ring contexts, embedding halves, the pipelined
/// describe) do so only when there are two.
pub fn cores() -> usize {
    static CORES: std::sync::LazyLock<usize> =
        std::sync::LazyLock::new(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    *CORES
}

/// Why a job did not run to completion.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PoolError {
    #[error("all {0} waiting slots are taken")]
    Full(usize),
    #[error("the deadline passed before the job finished")]
    Expired,
    #[error("the pool is shut down")]
    Closed,
    #[error("the job panicked")]
    Panicked,
}

/// Gauges of the pool.
#[derive(Debug, Default)]
pub struct PoolStats {
    pub queued: AtomicUsize,
    pub running: AtomicUsize,
    /// Refusals because every slot was taken, at submission or at [`CpuPool::check_room`] (since start).
    pub rejected: AtomicUsize,
    pub expired: AtomicUsize,
}

/// A fixed set of threads behind a bounded queue.
pub struct CpuPool {
    sender: Mutex<Option<SyncSender<Job>>>,
    threads: Mutex<Vec<JoinHandle<()>>>,
    queue: usize,
    /// `threads + queue`: jobs that may be in the pool, running or waiting.
    capacity: usize,
    /// Slots taken by jobs submitted and not yet finished.
    taken: Arc<AtomicUsize>,
    stats: Arc<PoolStats>,
}

/// One of the pool's slots, given back when the job that holds it is done or dropped.
struct Slot(Arc<AtomicUsize>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

impl CpuPool {
    /// `threads` workers; at most `queue` jobs wait for one.
    pub fn new(threads: usize, queue: usize) -> Self {
        let threads = threads.max(1);
        let capacity = threads + queue;
        // Every job in the channel holds a slot, so it never holds more than `capacity`.
        let (tx, rx) = sync_channel::<Job>(capacity);
        let rx = Arc::new(Mutex::new(rx));
        let stats = Arc::new(PoolStats::default());
        let handles = (0..threads)
            .map(|i| {
                let rx: Arc<Mutex<Receiver<Job>>> = Arc::clone(&rx);
                std::thread::Builder::new()
                    .name(format!("scone-cpu-{i}"))
                    .spawn(move || loop {
                        let job = rx.lock().recv();
                        match job {
                            Ok(job) => job(),
                            Err(_) => break,
                        }
                    })
                    .expect("spawning a worker thread")
            })
            .collect();
        Self {
            sender: Mutex::new(Some(tx)),
            threads: Mutex::new(handles),
            queue,
            capacity,
            taken: Arc::new(AtomicUsize::new(0)),
            stats,
        }
    }

    pub fn stats(&self) -> &PoolStats {
        &self.stats
    }

    /// Refuses ([`PoolError::Full`], counted as a rejection) when every slot is taken, so that a caller
    /// can refuse before it receives the job's input. Reserves nothing: [`CpuPool::run`] decides again.
    pub fn check_room(&self) -> Result<(), PoolError> {
        if self.taken.load(Ordering::Acquire) < self.capacity {
            Ok(())
        } else {
            self.stats.rejected.fetch_add(1, Ordering::Relaxed);
            Err(PoolError::Full(self.queue))
        }
    }

    fn take_slot(&self) -> Option<Slot> {
        self.taken
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| (n < self.capacity).then_some(n + 1))
            .ok()
            .map(|_| Slot(Arc::clone(&self.taken)))
    }

    /// Runs `f` on the pool and waits for it without blocking the async runtime. Refuses at once when every
    /// slot is taken; gives up waiting at `deadline` (a job not yet started then is skipped).
    pub async fn run<R, F>(&self, deadline: Instant, f: F) -> Result<R, PoolError>
    where
        R: Send + 'static,
        F: FnOnce() -> R + Send + 'static,
    {
        let Some(slot) = self.take_slot() else {
            self.stats.rejected.fetch_add(1, Ordering::Relaxed);
            return Err(PoolError::Full(self.queue));
        };
        let (tx, rx) = tokio::sync::oneshot::channel();
        let stats = Arc::clone(&self.stats);
        let job: Job = Box::new(move || {
            stats.queued.fetch_sub(1, Ordering::Relaxed);
            if Instant::now() >= deadline || tx.is_closed() {
                stats.expired.fetch_add(1, Ordering::Relaxed);
                return;
            }
            stats.running.fetch_add(1, Ordering::Relaxed);
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
            stats.running.fetch_sub(1, Ordering::Relaxed);
            // Free before answering: whoever sees the answer may submit at once.
            drop(slot);
            let _ = tx.send(r.map_err(|_| PoolError::Panicked));
        });
        {
            let sender = self.sender.lock();
            let Some(sender) = sender.as_ref() else { return Err(PoolError::Closed) };
            self.stats.queued.fetch_add(1, Ordering::Relaxed);
            if let Err(e) = sender.try_send(job) {
                self.stats.queued.fetch_sub(1, Ordering::Relaxed);
                // The job (and its slot) is dropped with the error.
                return Err(match e {
                    TrySendError::Full(_) => {
                        self.stats.rejected.fetch_add(1, Ordering::Relaxed);
                        PoolError::Full(self.queue)
                    }
                    TrySendError::Disconnected(_) => PoolError::Closed,
                });
            }
        }
        match tokio::time::timeout_at(deadline.into(), rx).await {
            Ok(Ok(r)) => r,
            Ok(Err(_)) | Err(_) => Err(PoolError::Expired),
        }
    }

    /// Stops taking jobs, lets the queued ones run, and joins the threads.
    pub fn shutdown(&self) {
        self.sender.lock().take();
        for h in self.threads.lock().drain(..) {
            let _ = h.join();
        }
    }
}

impl Drop for CpuPool {
    fn drop(&mut self) {
        self.sender.lock().take();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn rt() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_current_thread().enable_time().build().unwrap()
    }

    #[test]
    fn runs_jobs_and_returns_results() {
        let pool = CpuPool::new(2, 4);
        let r = rt().block_on(pool.run(Instant::now() + Duration::from_secs(5), || 6 * 7));
        assert_eq!(r, Ok(42));
    }

    #[test]
    fn refuses_when_the_queue_is_full() {
        let pool = Arc::new(CpuPool::new(1, 1));
        let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
        let gate_rx = Arc::new(Mutex::new(gate_rx));
        rt().block_on(async {
            let deadline = Instant::now() + Duration::from_secs(10);
            // One job occupies the thread, one fills the queue slot; the third is refused.
            let g = Arc::clone(&gate_rx);
            let p1 = Arc::clone(&pool);
            let first = tokio::spawn(async move { p1.run(deadline, move || g.lock().recv().is_ok()).await });
            while pool.stats().running.load(Ordering::Relaxed) == 0 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
            let p2 = Arc::clone(&pool);
            let second = tokio::spawn(async move { p2.run(deadline, || 2).await });
            while pool.stats().queued.load(Ordering::Relaxed) == 0 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
            assert_eq!(pool.run(deadline, || 3).await, Err(PoolError::Full(1)));
            assert_eq!(pool.stats().rejected.load(Ordering::Relaxed), 1);
            gate_tx.send(()).unwrap();
            assert_eq!(first.await.unwrap(), Ok(true));
            assert_eq!(second.await.unwrap(), Ok(2));
        });
    }

    #[test]
    fn check_room_refuses_exactly_when_every_slot_is_taken() {
        for queue in [0, 2] {
            let pool = Arc::new(CpuPool::new(1, queue));
            let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
            let gate_rx = Arc::new(Mutex::new(gate_rx));
            rt().block_on(async {
                let deadline = Instant::now() + Duration::from_secs(10);
                assert_eq!(pool.check_room(), Ok(()));
                let mut held = Vec::new();
                for i in 0..1 + queue {
                    let (g, p) = (Arc::clone(&gate_rx), Arc::clone(&pool));
                    held.push(tokio::spawn(async move { p.run(deadline, move || g.lock().recv().is_ok()).await }));
                    while pool.taken.load(Ordering::Acquire) <= i {
                        tokio::task::yield_now().await;
                    }
                    if i < queue {
                        assert_eq!(pool.check_room(), Ok(()), "queue {queue}: {} of {} slots taken", i + 1, 1 + queue);
                    }
                }
                assert_eq!(pool.check_room(), Err(PoolError::Full(queue)));
                assert_eq!(pool.run(deadline, || 0).await, Err(PoolError::Full(queue)));
                assert_eq!(pool.stats().rejected.load(Ordering::Relaxed), 2);
                for _ in 0..1 + queue {
                    gate_tx.send(()).unwrap();
                }
                for h in held {
                    assert_eq!(h.await.unwrap(), Ok(true));
                }
                // Every slot is given back once its job is done.
                assert_eq!(pool.check_room(), Ok(()));
                assert_eq!(pool.run(deadline, || 7).await, Ok(7));
            });
        }
    }

    #[test]
    fn a_job_whose_deadline_passed_in_the_queue_does_not_run() {
        let pool = Arc::new(CpuPool::new(1, 4));
        let ran = Arc::new(AtomicUsize::new(0));
        rt().block_on(async {
            let long = Instant::now() + Duration::from_secs(10);
            let p = Arc::clone(&pool);
            let blocker =
                tokio::spawn(async move { p.run(long, || std::thread::sleep(Duration::from_millis(200))).await });
            while pool.stats().running.load(Ordering::Relaxed) == 0 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
            let r = Arc::clone(&ran);
            let short = Instant::now() + Duration::from_millis(20);
            let out = pool
                .run(short, move || {
                    r.fetch_add(1, Ordering::Relaxed);
                })
                .await;
            assert_eq!(out, Err(PoolError::Expired));
            blocker.await.unwrap().unwrap();
        });
        pool.shutdown();
        assert_eq!(ran.load(Ordering::Relaxed), 0);
        assert_eq!(pool.stats().expired.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn a_panicking_job_is_reported_and_the_pool_keeps_working() {
        let pool = CpuPool::new(1, 2);
        let d = Instant::now() + Duration::from_secs(5);
        let rt = rt();
        assert_eq!(rt.block_on(pool.run(d, || -> u8 { panic!("boom") })), Err(PoolError::Panicked));
        assert_eq!(rt.block_on(pool.run(d, || 1)), Ok(1));
    }
}

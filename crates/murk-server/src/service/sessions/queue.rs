//! A session's frame queue between the stream reader and the computing worker, under the
//! session's policy: LATEST pushes out the oldest waiting frame, FIFO makes the reader wait
//! (and so stop reading the stream, which HTTP/2 flow control turns into backpressure on the
//! sender).

use std::collections::VecDeque;
use std::sync::Mutex;
use std::time::Instant;

use tokio::sync::Notify;

use crate::service::proto::v1 as pb;

/// A frame waiting for its turn.
#[derive(Debug)]
pub struct Queued {
    /// The frame as received.
    pub frame: pb::SessionFrame,
    /// When it arrived.
    pub arrived: Instant,
}

#[derive(Debug, Default)]
struct State {
    frames: VecDeque<Queued>,
    closed: bool,
}

/// The queue. One reader pushes, one worker pops.
#[derive(Debug)]
pub struct FrameQueue {
    state: Mutex<State>,
    capacity: usize,
    latest: bool,
    /// A frame was pushed, or the queue closed.
    ready: Notify,
    /// A frame was popped (FIFO's reader waits on it).
    space: Notify,
}

impl FrameQueue {
    /// A queue of `capacity ≥ 1` frames under `policy` (LATEST or FIFO).
    pub fn new(capacity: usize, policy: pb::QueuePolicy) -> Self {
        Self {
            state: Mutex::new(State::default()),
            capacity: capacity.max(1),
            latest: policy != pb::QueuePolicy::Fifo,
            ready: Notify::new(),
            space: Notify::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues `frame`. Under LATEST a full queue gives up its oldest frame, returned for the
    /// drop report; under FIFO this waits for space.
    pub async fn push(&self, frame: Queued) -> Option<Queued> {
        let mut frame = Some(frame);
        loop {
            {
                let mut s = self.lock();
                if s.frames.len() < self.capacity || self.latest {
                    let dropped = if s.frames.len() >= self.capacity {
                        s.frames.pop_front()
                    } else {
                        None
                    };
                    s.frames.extend(frame.take());
                    drop(s);
                    self.ready.notify_one();
                    return dropped;
                }
            }
            // One waiter per side, and `notify_one` keeps a permit when nobody waits yet, so a
            // pop between the check and this wait is not lost.
            self.space.notified().await;
        }
    }

    /// The next frame; `None` once the queue is closed and empty.
    pub async fn pop(&self) -> Option<Queued> {
        loop {
            {
                let mut s = self.lock();
                if let Some(f) = s.frames.pop_front() {
                    drop(s);
                    self.space.notify_one();
                    return Some(f);
                }
                if s.closed {
                    return None;
                }
            }
            self.ready.notified().await;
        }
    }

    /// Waits until a frame is queued, without taking it: true then, false once the queue is
    /// closed and empty. (The worker waits here, then for its turn to compute, then pops: under
    /// LATEST the frame it pops is the newest that arrived meanwhile.)
    pub async fn wait_ready(&self) -> bool {
        loop {
            {
                let s = self.lock();
                if !s.frames.is_empty() {
                    return true;
                }
                if s.closed {
                    return false;
                }
            }
            self.ready.notified().await;
        }
    }

    /// No more frames will come; the worker finishes those queued.
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_one();
    }

    /// Frames waiting.
    pub fn len(&self) -> usize {
        self.lock().frames.len()
    }

    /// True when no frame waits.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(sequence: u64) -> Queued {
        Queued {
            frame: pb::SessionFrame {
                sequence,
                ..Default::default()
            },
            arrived: Instant::now(),
        }
    }

    #[tokio::test]
    async fn latest_drops_the_oldest_and_keeps_order() {
        let q = FrameQueue::new(2, pb::QueuePolicy::Latest);
        assert!(q.push(frame(1)).await.is_none());
        assert!(q.push(frame(2)).await.is_none());
        assert_eq!(q.push(frame(3)).await.unwrap().frame.sequence, 1);
        assert_eq!(q.push(frame(4)).await.unwrap().frame.sequence, 2);
        q.close();
        assert_eq!(q.pop().await.unwrap().frame.sequence, 3);
        assert_eq!(q.pop().await.unwrap().frame.sequence, 4);
        assert!(q.pop().await.is_none());
    }

    #[tokio::test]
    async fn waiting_for_a_frame_leaves_it_for_the_newest_to_replace() {
        let q = std::sync::Arc::new(FrameQueue::new(1, pb::QueuePolicy::Latest));
        let waiter = {
            let q = q.clone();
            tokio::spawn(async move { q.wait_ready().await })
        };
        assert!(q.push(frame(1)).await.is_none());
        assert!(waiter.await.unwrap());
        // The worker waited without taking frame 1, so a newer frame replaces it before the pop.
        assert_eq!(q.push(frame(2)).await.unwrap().frame.sequence, 1);
        assert!(q.wait_ready().await);
        assert_eq!(q.pop().await.unwrap().frame.sequence, 2);
        q.close();
        assert!(!q.wait_ready().await, "closed and empty");
    }

    #[tokio::test]
    async fn fifo_waits_for_space_and_drops_nothing() {
        let q = std::sync::Arc::new(FrameQueue::new(1, pb::QueuePolicy::Fifo));
        assert!(q.push(frame(1)).await.is_none());
        let pusher = {
            let q = q.clone();
            tokio::spawn(async move { q.push(frame(2)).await.is_none() })
        };
        // The second push cannot finish until a frame leaves.
        tokio::task::yield_now().await;
        assert!(!pusher.is_finished());
        assert_eq!(q.pop().await.unwrap().frame.sequence, 1);
        assert!(pusher.await.unwrap());
        assert_eq!(q.len(), 1);
        q.close();
        assert_eq!(q.pop().await.unwrap().frame.sequence, 2);
        assert!(q.pop().await.is_none());
    }
}

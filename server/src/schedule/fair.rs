//! The order in which queued work is served: one queue per flow (a tenant on a device), served by weighted fair
//! queuing. Each flow has a virtual `pass`; serving a task of `cost` advances its flow's pass by `cost / share`,
//! and the flow with the smallest pass is served next. A flow that was idle starts at the current virtual time, so
//! idleness earns no credit and a newcomer waits at most for the tasks already being served.
//!
//! Costs are rays, so two flows with equal shares get equal rays, whatever their batch sizes: a flow that sends one
//! ray at a time is served ahead of a flow with a million queued.

use std::collections::BTreeMap;
use std::sync::Arc;

/// Who queued a task, and its weight.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Flow {
    /// The tenant's name.
    pub name: Arc<str>,
    /// Its weight: a flow with share 2 is served twice the rays of a flow with share 1 while both have work.
    pub share: u32,
}

/// One flow's queue and place in virtual time.
#[derive(Debug)]
struct FlowQueue<T> {
    /// Virtual time at which its next task starts.
    pass: f64,
    /// Its waiting tasks with their costs, by their order and then by arrival.
    tasks: BTreeMap<(u64, u64), (u64, T)>,
}

/// Tasks of many flows, taken out fairly.
#[derive(Debug)]
pub struct FairQueue<T> {
    /// Every flow seen, by name (ordered, so ties are broken the same way every time).
    flows: BTreeMap<Arc<str>, FlowQueue<T>>,
    /// The virtual time: the start of the task served last.
    now: f64,
    /// Tasks waiting in all flows.
    len: usize,
    /// Tasks pushed so far: the arrival number of the next.
    pushed: u64,
}

impl<T> Default for FairQueue<T> {
    fn default() -> Self {
        FairQueue { flows: BTreeMap::new(), now: 0.0, len: 0, pushed: 0 }
    }
}

impl<T> FairQueue<T> {
    /// Whether no task waits.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Tasks waiting.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Queues `task` of `cost` (rays) among the tasks of `flow`: behind those of the same or a smaller `order`, ahead
    /// of those of a larger one (a trace's pieces, queued one at a time, all have its order: the trace's arrival, so
    /// that a flow's traces are served in arrival order).
    pub fn push(&mut self, flow: &Flow, order: u64, cost: u64, task: T) {
        let now = self.now;
        let queue =
            self.flows.entry(Arc::clone(&flow.name)).or_insert_with(|| FlowQueue { pass: now, tasks: BTreeMap::new() });
        if queue.tasks.is_empty() {
            queue.pass = queue.pass.max(now);
        }
        queue.tasks.insert((order, self.pushed), (cost.max(1) * SHARE_SCALE / u64::from(flow.share.max(1)), task));
        self.pushed += 1;
        self.len += 1;
    }

    /// Takes the next task: the first waiting one of the flow whose pass is smallest.
    pub fn pop(&mut self) -> Option<T> {
        let queue = self.flows.values_mut().filter(|q| !q.tasks.is_empty()).min_by(|a, b| a.pass.total_cmp(&b.pass))?;
        let (_, (weighted_cost, task)) = queue.tasks.pop_first()?;
        self.now = queue.pass;
        queue.pass += weighted_cost as f64;
        self.len -= 1;
        Some(task)
    }
}

/// Costs are divided by shares in fixed point, so shares up to this value divide exactly.
const SHARE_SCALE: u64 = 1 << 20;

#[cfg(test)]
mod tests {
    use super::*;

    fn flow(name: &str, share: u32) -> Flow {
        Flow { name: name.into(), share }
    }

    /// Pops everything and returns the flow names in the order served.
    fn drain(queue: &mut FairQueue<&'static str>) -> Vec<&'static str> {
        std::iter::from_fn(|| queue.pop()).collect()
    }

    #[test]
    fn a_newcomer_is_served_next_however_much_another_flow_has_queued() {
        let mut queue = FairQueue::default();
        let flood = flow("a", 1);
        for _ in 0..1000 {
            queue.push(&flood, 0, 1024, "a");
        }
        for _ in 0..10 {
            assert_eq!(queue.pop(), Some("a"));
        }
        queue.push(&flow("b", 1), 0, 1, "b");
        assert_eq!(queue.pop(), Some("b"), "one ray of b goes before the rest of a's million");
        assert_eq!(queue.len(), 990);
    }

    #[test]
    fn busy_flows_get_rays_in_proportion_to_their_shares() {
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 3));
        for _ in 0..400 {
            queue.push(&a, 0, 100, "a");
            queue.push(&b, 0, 100, "b");
        }
        let first: Vec<_> = drain(&mut queue).into_iter().take(400).collect();
        let served_b = first.iter().filter(|&&n| n == "b").count();
        assert!((299..=301).contains(&served_b), "b has 3 of 4 shares: {served_b} of 400");
    }

    #[test]
    fn equal_shares_split_rays_not_tasks() {
        let mut queue = FairQueue::default();
        let (big, small) = (flow("big", 1), flow("small", 1));
        for _ in 0..100 {
            queue.push(&big, 0, 1000, "big");
        }
        for _ in 0..1000 {
            queue.push(&small, 0, 100, "small");
        }
        // While both have work, each gets about half the rays: one big task for every ten small ones.
        let order = drain(&mut queue);
        let window = &order[..550];
        let big_rays = window.iter().filter(|&&n| n == "big").count() * 1000;
        let small_rays = window.iter().filter(|&&n| n == "small").count() * 100;
        assert!(big_rays.abs_diff(small_rays) <= 1000, "{big_rays} against {small_rays}");
    }

    #[test]
    fn idle_time_earns_no_credit() {
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 1));
        queue.push(&b, 0, 10, "b");
        assert_eq!(queue.pop(), Some("b"));
        for _ in 0..100 {
            queue.push(&a, 0, 10, "a");
        }
        for _ in 0..50 {
            queue.pop();
        }
        // b was idle while a was served 50 times: it now alternates with a instead of running 50 in a row.
        for _ in 0..10 {
            queue.push(&b, 0, 10, "b");
        }
        let next: Vec<_> = drain(&mut queue).into_iter().take(20).collect();
        let run_of_b = next.iter().take_while(|&&n| n == "b").count();
        assert!(run_of_b <= 1, "{next:?}");
        assert_eq!(next.iter().filter(|&&n| n == "b").count(), 10, "{next:?}");
    }

    #[test]
    fn one_flow_keeps_its_order() {
        let mut queue = FairQueue::default();
        let a = flow("a", 5);
        for name in ["1", "2", "3"] {
            queue.push(&a, 0, 7, name);
        }
        assert_eq!(drain(&mut queue), ["1", "2", "3"]);
        assert!(queue.is_empty());
    }

    #[test]
    fn a_later_task_of_an_earlier_order_goes_first_within_its_flow() {
        // Trace 1's second piece is queued after trace 2's first: it is still served first.
        let mut queue = FairQueue::default();
        let a = flow("a", 1);
        queue.push(&a, 1, 7, "1a");
        assert_eq!(queue.pop(), Some("1a"));
        queue.push(&a, 2, 7, "2a");
        queue.push(&a, 1, 7, "1b");
        queue.push(&a, 2, 7, "2b");
        assert_eq!(drain(&mut queue), ["1b", "2a", "2b"]);
    }
}

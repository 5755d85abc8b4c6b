//! # pathfarm-farm
//!
//! The render farm: a coordinator that schedules the passes of guided jobs over worker
//! processes, and the workers that render them.
//!
//! * [`scheduler`]: pure lease bookkeeping (jobs, tasks, workers, deadlines, attempts) with an
//!   injected clock; no sockets, no I/O.
//! * [`driver`]: one job's progress through its session (units, records, inputs published),
//!   pure, shared by the coordinator and the simulation.
//! * [`codec`]: binary forms of fractions, estimates, tile pixels; pass specs as proto.
//! * [`bundle`]: scene bundles: a scene file and every file it references, content-addressed.

pub mod build;
pub mod bundle;
mod chunked;
pub mod client;
pub mod codec;
pub mod coordinator;
pub mod driver;
pub mod scheduler;
pub mod tiling;
pub mod worker;

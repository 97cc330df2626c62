//! End-to-end tests: they run the real binaries and read what they write, with our own reader
//! and with the reference Python clients.

mod crash_safety;
mod docs;
mod fuzz;
mod mfusenet;
mod record_adaptive;
mod record_cli;
mod record_geometry;
mod record_ground_truth;
mod record_import;
mod record_log;
mod replay_check;
mod replay_eval;
mod replay_input;
mod replay_plan;
mod replay_watch;
mod ros2_bags;
mod signed_ranges;
mod viz_rerun;

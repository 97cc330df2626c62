//! `record --rig adaptive`: the closed loop of next-best-view capture. The log holds every view
//! with its pose and each plan on `/capture/plan` (read by our reader, the `mcap` crate and
//! Python `mcap`); MFuseNet's plans make layouts its networks take; replay runs on the sets.

use std::process::Command;

use multiscopic_tests::{Log, assert_success, python_with_mcap, recorded, replay_summary, run, temp_dir};

fn plans(log: &Log) -> Vec<serde_json::Value> {
    log.messages
        .iter()
        .filter(|m| m.topic == "/capture/plan")
        .map(|m| serde_json::from_slice(&m.data).unwrap_or_else(|e| panic!("a plan that is not JSON: {e}")))
        .collect()
}

#[test]
fn every_view_has_its_plan_and_the_plans_choose_reachable_views_not_yet_taken() {
    let (_dir, path) = recorded(
        "adaptive.mcap",
        "--rig adaptive --views 4 --plan-method sgm-heuristic --plan-max-offset 2 --resolution 160x120 \
         --samples-per-pixel 1",
    );
    let log = Log::read(&path);
    let plans = plans(&log);
    // Three planned neighbours.
    assert_eq!(plans.len(), 3, "{plans:#?}");
    let events = log.events();
    assert_eq!(events.len(), 4, "a set of four views");
    for plan in &plans {
        let set = plan["set_index"].as_u64().unwrap_or(99) as u32;
        let chosen = &plan["chosen_offset"];
        // Offsets in the plan's baseline (a set whose offsets share a factor is stored at that
        // multiple of the baseline).
        let plan_baseline_m = plan["baseline_m"].as_f64().unwrap_or(f64::NAN);
        let offsets: Vec<serde_json::Value> = events
            .iter()
            .filter(|e| e.set_index == set)
            .map(|e| {
                let factor = (e.baseline_m / plan_baseline_m).round() as i32;
                serde_json::json!(e.grid_offset.map(|o| o * factor))
            })
            .collect();
        assert!(
            offsets.contains(chosen),
            "the chosen view {chosen} is in set {set}: {offsets:?}"
        );
        assert!(!plan["taken"].as_array().is_some_and(|t| t.contains(chosen)), "{plan}");
        let candidates = plan["candidates"].as_array().cloned().unwrap_or_default();
        assert!(!candidates.is_empty(), "{plan}");
        let picked = candidates
            .iter()
            .find(|c| c["offsets"][0] == *chosen)
            .unwrap_or_else(|| panic!("the choice is among the candidates: {plan}"));
        assert_eq!(picked["reachable"], true, "{picked}");
        assert_eq!(picked["feasible"], true, "{picked}");
        // The first is planned from texture and the working range, the others from the method's estimate.
        let first = plan["step"] == 1;
        assert_eq!(plan["method"].is_null(), first, "{plan}");
    }
    let script = multiscopic_tests::workspace_root().join("tests/python/read_plans.py");
    let output = run(Command::new(python_with_mcap()).arg(script).arg(&path));
    assert_success(&output, "python mcap reads the plans");
    assert_eq!(String::from_utf8_lossy(&output.stdout).trim(), "3 plans");
    // Replay runs every method on the irregular sets it made.
    let out = temp_dir();
    let summary = replay_summary(&path, out.path(), "--method sgm-heuristic,bm-heuristic,gc-heuristic");
    let runs = summary["sets"].as_array().cloned().unwrap_or_default();
    assert_eq!(runs.len(), 3, "one set × three methods: {summary}");
    for r in &runs {
        let avg = r["outputs"]["metrics"]["all"]["avg_err_px"]
            .as_f64()
            .unwrap_or(f64::NAN);
        assert!(
            avg.is_finite() && avg < 5.0,
            "{} on {}: AvgErr {avg}",
            r["method"],
            r["name"]
        );
    }
}

#[test]
fn mfusenet_plans_make_a_layout_its_networks_take() {
    let (_dir, path) = recorded(
        "adaptive3.mcap",
        "--rig adaptive --views 3 --resolution 160x120 --samples-per-pixel 1",
    );
    let log = Log::read(&path);
    let offsets: Vec<[i32; 2]> = log
        .events()
        .iter()
        .map(|e| e.grid_offset)
        .filter(|o| *o != [0, 0])
        .collect();
    assert_eq!(offsets.len(), 2, "{offsets:?}");
    assert_eq!(
        offsets[0],
        [-offsets[1][0], -offsets[1][1]],
        "an opposite pair: {offsets:?}"
    );
    // The toy's working range fits twice the baseline in the search (16 px at 160 px wide): the
    // planner took it, and the set is stored at 40 mm, its range with it, which replay searches.
    let event = &log.events()[0];
    assert!((event.baseline_m - 0.04).abs() < 1e-9, "{event:?}");
    let range = event
        .disparity_range
        .as_ref()
        .unwrap_or_else(|| panic!("no range: {event:?}"));
    assert!(range.min_disparity > 0, "{range:?}");
    let out = temp_dir();
    let summary = replay_summary(&path, out.path(), "--method mfusenet");
    let text = summary.to_string();
    assert!(
        text.contains("three-view"),
        "MFuseNet took its three-view network: {text}"
    );
}

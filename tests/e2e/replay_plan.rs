//! `replay plan`: the next best views of a recorded set, with their poses checked against the arm.

use multiscopic_tests::{assert_success, recorded, replay};

fn plan(log: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["plan", log.to_str().unwrap_or_default(), "--json", "-q"];
    args.extend_from_slice(extra);
    let output = replay(&args);
    assert_success(&output, "replay plan");
    serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("replay plan printed no JSON: {e}"))
}

#[test]
fn the_plan_proposes_reachable_views_not_yet_taken_best_first() {
    let (_dir, log) = recorded("five.mcap", "--resolution 192x144 --samples-per-pixel 1");
    let plan = plan(
        &log,
        &["--neighbours", "left", "--method", "sgm-heuristic", "--budget", "3"],
    );
    assert_eq!(plan["layout"], "free", "{plan}");
    assert_eq!(plan["taken"], serde_json::json!([[-1, 0]]), "{plan}");
    let chosen = plan["chosen"].as_array().cloned().unwrap_or_default();
    assert_eq!(chosen.len(), 3, "{plan}");
    let candidates = plan["candidates"].as_array().cloned().unwrap_or_default();
    // 8 directions × 2 lengths, less the view taken.
    assert_eq!(candidates.len(), 15, "{plan}");
    let gains: Vec<f64> = candidates
        .iter()
        .map(|c| c["expected_pixels"].as_f64().unwrap_or(f64::NAN))
        .collect();
    assert!(gains.windows(2).all(|w| w[0] >= w[1]), "best first: {gains:?}");
    for c in &chosen {
        let poses = c["poses"].as_array().cloned().unwrap_or_default();
        assert_eq!(poses.len(), 1, "{c}");
        let pose = &poses[0];
        assert_ne!(pose["offset"], serde_json::json!([-1, 0]), "a view already taken: {c}");
        assert_eq!(pose["reachable"], true, "{c}");
        assert_eq!(pose["joints_rad"].as_array().map(Vec::len), Some(6), "{c}");
        assert!(pose["table_clearance_m"].as_f64().is_some_and(|z| z > 0.0), "{c}");
        assert!(c["gain"].as_f64().is_some_and(|g| g > 0.0), "{c}");
    }
    let (method, planning) = (
        plan["method_seconds"].as_f64().unwrap_or(f64::NAN),
        plan["planning_seconds"].as_f64().unwrap_or(f64::NAN),
    );
    println!("sgm-heuristic {method:.3} s, planning {planning:.3} s");
}

#[test]
fn mfusenet_plans_opposite_pairs_and_a_missing_set_is_a_usage_error() {
    let (_dir, log) = recorded("five.mcap", "--resolution 160x120 --samples-per-pixel 1");
    let plan = plan(&log, &["--neighbours", "left,right", "--budget", "1"]);
    assert_eq!(plan["method"], "mfusenet", "{plan}");
    assert_eq!(plan["layout"], "pairs", "{plan}");
    let chosen = plan["chosen"].as_array().cloned().unwrap_or_default();
    assert_eq!(chosen.len(), 1, "{plan}");
    // With left and right taken at one baseline, the pair that completes a five-view layout.
    let offsets = &chosen[0]["offsets"];
    assert_eq!(offsets, &serde_json::json!([[0, 1], [0, -1]]), "{plan}");
    let missing = replay(&["plan", log.to_str().unwrap_or_default(), "--set", "7"]);
    assert_eq!(
        missing.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&missing.stderr)
    );
    assert!(String::from_utf8_lossy(&missing.stderr).contains("no set 7"));
}

//! `replay`: reads multiscopic logs written by `record` (or foreign logs with the same Foxglove
//! topics), rebuilds the aligned view sets, checks their alignment, runs the fusion methods of
//! `fuse` and evaluates them against ground truth.
//!
//! It starts with the first step of that path: reading the capture events of a log and grouping
//! them into view sets.

use std::collections::BTreeMap;

use record::log::{CAPTURE_EVENTS_TOPIC, CaptureEvent};

/// Errors reading a log.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The bytes are not a readable MCAP log.
    #[error("not a readable MCAP log: {source}")]
    Mcap {
        /// Cause.
        #[source]
        source: mcap::McapError,
    },
    /// A capture event does not parse.
    #[error("capture event at log time {log_time} on {topic} is malformed: {source}")]
    BadEvent {
        /// Topic.
        topic: &'static str,
        /// Log time (ns).
        log_time: u64,
        /// Cause.
        #[source]
        source: serde_json::Error,
    },
}

/// The capture events of one set, reference first.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewSetEvents {
    /// Set index.
    pub set_index: u32,
    /// Events, the `center` view first, then in capture order.
    pub views: Vec<CaptureEvent>,
}

/// Reads every capture event of a log (linear scan of the messages).
pub fn read_capture_events(mcap_bytes: &[u8]) -> Result<Vec<CaptureEvent>, ReplayError> {
    let stream =
        mcap::MessageStream::new(mcap_bytes).map_err(|source| ReplayError::Mcap { source })?;
    let mut events = Vec::new();
    for message in stream {
        let message = message.map_err(|source| ReplayError::Mcap { source })?;
        if message.channel.topic != CAPTURE_EVENTS_TOPIC {
            continue;
        }
        let event =
            serde_json::from_slice(&message.data).map_err(|source| ReplayError::BadEvent {
                topic: CAPTURE_EVENTS_TOPIC,
                log_time: message.log_time,
                source,
            })?;
        events.push(event);
    }
    Ok(events)
}

/// Groups events into sets by `set_index`, the reference (`center`) view first.
pub fn group_sets(events: Vec<CaptureEvent>) -> Vec<ViewSetEvents> {
    let mut sets: BTreeMap<u32, Vec<CaptureEvent>> = BTreeMap::new();
    for event in events {
        sets.entry(event.set_index).or_default().push(event);
    }
    sets.into_iter()
        .map(|(set_index, mut views)| {
            views.sort_by_key(|e| (e.role != record::rig::REFERENCE_ROLE, e.capture_time_nanos));
            ViewSetEvents { set_index, views }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use record::camera::PinholeCamera;
    use record::rig::RigKind;
    use record::{CapturedSet, CapturedView};

    fn set(index: u32) -> CapturedSet {
        let camera = PinholeCamera::from_horizontal_fov(4, 3, 60.0);
        let view = |role: &str, dx: i32, time: u64| CapturedView {
            role: role.into(),
            grid_offset: [dx, 0],
            camera,
            capture_time_nanos: time,
            rgb: vec![7; 36],
            depth_m: Some(vec![0.5; 12]),
            surface_class: None,
            world_from_camera: nalgebra::Isometry3::translation(f64::from(dx) * 0.02, 0.0, 0.0),
            world_from_camera_true: None,
            commanded_world_from_camera: None,
            joints: None,
            exposure_gain: 1.0,
        };
        let t = u64::from(index) * 1_000;
        CapturedSet {
            index,
            name: format!("s{index}"),
            rig: RigKind::ThreeView,
            baseline_m: 0.02,
            motion: Vec::new(),
            views: vec![
                view("left", -1, t + 1),
                view("center", 0, t + 2),
                view("right", 1, t + 3),
            ],
        }
    }

    #[test]
    fn events_round_trip_through_an_in_memory_log() {
        let mut writer = record::log::LogOptions::new()
            .create(std::io::Cursor::new(Vec::new()))
            .unwrap_or_else(|e| panic!("{e}"));
        for index in 0..2 {
            writer
                .write_set(&set(index), None)
                .unwrap_or_else(|e| panic!("{e}"));
        }
        let bytes = writer
            .finish()
            .unwrap_or_else(|e| panic!("{e}"))
            .into_inner();
        let sets = group_sets(read_capture_events(&bytes).unwrap_or_else(|e| panic!("{e}")));
        assert_eq!(sets.len(), 2);
        for (index, set) in sets.iter().enumerate() {
            assert_eq!(set.set_index, index as u32);
            let roles: Vec<&str> = set.views.iter().map(|e| e.role.as_str()).collect();
            assert_eq!(roles, ["center", "left", "right"]);
            assert_eq!(
                set.views[0].depth_topic.as_deref(),
                Some("/camera/center/ground_truth/depth")
            );
            assert!((set.views[1].world_from_camera.translation_m[0] + 0.02).abs() < 1e-12);
        }
    }

    #[test]
    fn garbage_is_an_error_not_a_panic() {
        assert!(matches!(
            read_capture_events(b"not an mcap file"),
            Err(ReplayError::Mcap { .. })
        ));
    }
}

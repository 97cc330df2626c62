//! A viewer layout for a capture log opened as it is: `rerun capture.mcap capture.rbl`.
//!
//! Rerun's MCAP importer maps the recorder's Foxglove schemas onto its own archetypes
//! (`RawImage` → `Image`, `CameraCalibration` → `Pinhole`, `FrameTransforms` → `Transform3D`), but
//! an MCAP carries no layout: opened alone, the viewer guesses one view per topic and starts at the
//! first instant of the log, before any image exists. A blueprint file beside the log gives it the
//! 3D scene (the cameras' frustums at their poses) next to the views in a grid, opened at the end
//! of the capture.
//!
//! The viewer applies a blueprint to recordings of the same application id, and names a recording
//! imported from a file after the file's stem ([`app_id_for_log`]).

use std::path::{Path, PathBuf};

use rerun::blueprint::components::{PanelState, PlayState};
use rerun::blueprint::{
    Blueprint, BlueprintActivation, BlueprintPanel, ContainerLike, Grid, Horizontal, SelectionPanel, Spatial2DView,
    Spatial3DView, Tabs, TimePanel,
};
use rerun::{ApplicationId, RecordingStreamBuilder};

use crate::stream::VizError;

/// The timeline the viewer's MCAP importer puts messages on (their MCAP `log_time`).
pub const MCAP_LOG_TIMELINE: &str = "message_log_time";

/// Extension of Rerun blueprint files.
pub const BLUEPRINT_EXTENSION: &str = "rbl";

/// One camera of a capture log as the viewer imports it: entity paths are the MCAP topics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LogView {
    /// Role (`center`, `left`, …), the view's title.
    pub role: String,
    /// Entity (topic) of its image.
    pub image_entity: String,
    /// Entity (topic) of its ground-truth depth, when the log has one.
    pub depth_entity: Option<String>,
    /// Other images in the camera's image plane (e.g. surface classes): kept out of the 3D
    /// scene, where they would cover the image.
    pub hidden_in_3d: Vec<String>,
}

/// What the layout shows.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogLayout {
    /// The cameras, reference first.
    pub views: Vec<LogView>,
    /// Distance of the image planes drawn in the 3D scene (m). The viewer sizes frustums to the
    /// whole scene, which makes a rig a few centimetres wide a cluster of dots; a distance that
    /// draws each image a little narrower than the baseline shows the views side by side.
    pub image_plane_distance_m: Option<f32>,
}

/// The application id the viewer gives a log it imports from `log_path`: the file stem with dots
/// replaced by `_` (what `rerun`'s file importer does), normalised like every application id.
pub fn app_id_for_log(log_path: &Path) -> Result<ApplicationId, VizError> {
    let stem = log_path
        .file_stem()
        .map(|s| s.to_string_lossy().replace('.', "_"))
        .unwrap_or_default();
    ApplicationId::try_new(stem).map_err(|e| VizError::Save {
        path: log_path.to_path_buf(),
        reason: format!("no application id from the file name: {e}"),
    })
}

/// Where the blueprint of the log at `log_path` goes: beside it, `<stem>.rbl`.
pub fn blueprint_path_for_log(log_path: &Path) -> PathBuf {
    log_path.with_extension(BLUEPRINT_EXTENSION)
}

/// The layout: the 3D scene on the left; on the right the views' images in a grid, with a second
/// tab for their ground-truth depth when the log has it; panels collapsed; opened following the
/// end of the log's timeline.
pub fn log_blueprint(layout: &LogLayout) -> Blueprint {
    let views = &layout.views;
    let images: Vec<ContainerLike> = views
        .iter()
        .map(|view| {
            Spatial2DView::new(view.role.as_str())
                .with_origin(view.image_entity.as_str())
                .into()
        })
        .collect();
    let depths: Vec<ContainerLike> = views
        .iter()
        .filter_map(|view| {
            let entity = view.depth_entity.as_deref()?;
            Some(
                Spatial2DView::new(format!("{} depth", view.role))
                    .with_origin(entity)
                    .into(),
            )
        })
        .collect();
    let mut tabs = vec![ContainerLike::from(Grid::new(images).with_name("images"))];
    if !depths.is_empty() {
        tabs.push(Grid::new(depths).with_name("ground-truth depth").into());
    }
    // The cameras with their images; depth maps would cover the images in the same planes.
    let contents = std::iter::once("+ /**".to_owned()).chain(views.iter().flat_map(|view| {
        view.depth_entity
            .iter()
            .chain(&view.hidden_in_3d)
            .map(|entity| format!("- {entity}"))
    }));
    let mut scene = Spatial3DView::new("3D scene").with_origin("/").with_contents(contents);
    if let Some(distance) = layout.image_plane_distance_m {
        scene = scene.with_defaults(&rerun::Pinhole::update_fields().with_image_plane_distance(distance));
    }
    Blueprint::new(Horizontal::new([
        ContainerLike::from(scene),
        ContainerLike::from(Tabs::new(tabs)),
    ]))
    .with_blueprint_panel(BlueprintPanel::new().with_state(PanelState::Collapsed))
    .with_selection_panel(SelectionPanel::new().with_state(PanelState::Collapsed))
    .with_time_panel(
        TimePanel::new()
            .with_timeline(MCAP_LOG_TIMELINE)
            .with_play_state(PlayState::Following),
    )
}

/// Writes [`log_blueprint`] for the recording `app_id` to `path` (an `.rbl` file the viewer opens
/// beside the log and makes the default layout of that application).
pub fn save_log_blueprint(path: &Path, app_id: ApplicationId, layout: &LogLayout) -> Result<(), VizError> {
    let save_error = |reason: String| VizError::Save {
        path: path.to_path_buf(),
        reason,
    };
    let stream = RecordingStreamBuilder::new(app_id)
        .blueprint()
        .save(path)
        .map_err(|e| save_error(e.to_string()))?;
    log_blueprint(layout)
        .send(
            &stream,
            BlueprintActivation {
                make_active: true,
                make_default: true,
            },
        )
        .map_err(|e| save_error(e.to_string()))?;
    stream.flush_blocking().map_err(|e| save_error(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn app_ids_follow_the_viewers_file_importer() -> Result<(), VizError> {
        assert_eq!(app_id_for_log(Path::new("runs/capture.mcap"))?.as_str(), "capture");
        assert_eq!(app_id_for_log(Path::new("a.b.mcap"))?.as_str(), "a_b");
        assert!(app_id_for_log(Path::new("")).is_err());
        assert_eq!(
            blueprint_path_for_log(Path::new("runs/capture.mcap")),
            PathBuf::from("runs/capture.rbl")
        );
        Ok(())
    }

    #[test]
    fn a_saved_blueprint_is_a_rerun_file() -> Result<(), Box<dyn std::error::Error>> {
        let dir = std::env::temp_dir().join(format!("viz-log-blueprint-{}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        let path = dir.join("capture.rbl");
        let layout = LogLayout {
            views: ["center", "left"]
                .map(|role| LogView {
                    role: role.to_owned(),
                    image_entity: format!("/camera/{role}/image"),
                    depth_entity: Some(format!("/camera/{role}/ground_truth/depth")),
                    hidden_in_3d: vec![format!("/camera/{role}/ground_truth/surface")],
                })
                .to_vec(),
            image_plane_distance_m: Some(0.02),
        };
        save_log_blueprint(&path, app_id_for_log(Path::new("capture.mcap"))?, &layout)?;
        let bytes = std::fs::read(&path)?;
        std::fs::remove_dir_all(&dir)?;
        // An RRD stream starts with its magic ("RRF2"); the layout makes it more than a header.
        assert_eq!(bytes.get(..4), Some(&b"RRF2"[..]), "not an RRD stream");
        assert!(bytes.len() > 1000, "{} bytes only", bytes.len());
        Ok(())
    }
}

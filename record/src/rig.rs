//! Multiscopic rig layouts: which views a set has, their roles and their offsets on the grid of
//! camera positions (in baselines, along the reference camera's own x and y axes).

use serde::{Deserialize, Serialize};

/// The role of the reference view in every layout.
pub const REFERENCE_ROLE: &str = "center";

/// Rig layouts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum RigKind {
    /// Centre, left, right, top, bottom (the paper's five-view rig).
    FiveView,
    /// Left, centre, right on one horizontal line (the paper's Middlebury setting).
    ThreeView,
    /// Centre (reference) and right: two-view stereo.
    Stereo,
    /// 3 × 3 grid of views around the centre.
    #[value(name = "grid3x3")]
    #[serde(rename = "grid3x3")]
    Grid3x3,
    /// Five views on a horizontal line at −2 … 2 baselines (Tsukuba's row of five): the centre,
    /// `left`, `right` and, at twice the baseline, `left2` and `right2`.
    #[value(name = "line5")]
    #[serde(rename = "line5")]
    Line5,
    /// The 3 × 3 grid and, at twice the baseline, the cross `left2`, `right2`, `top2`, `bottom2`:
    /// 13 views, every offset a line, a cross or a grid of up to two baselines has (the training
    /// captures of the view-count-agnostic MFuseNet).
    #[value(name = "grid-cross")]
    #[serde(rename = "grid-cross")]
    GridCross,
    /// The centre, then each next view where a plan from the depth so far says it resolves most
    /// (next-best-view capture with `--views N`; not a layout to import)
    // Only the centre is fixed: `capture_order` lists it alone (`crate::adaptive` plans the rest).
    Adaptive,
}

/// One view position of a rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ViewSlot {
    /// Role name, readable in topics and entity paths (`center`, `left`, `top-right`, …).
    pub role: &'static str,
    /// Offset in baselines: `[dx, dy]` along the reference camera's x (right) and y (down) axes.
    pub grid_offset: [i32; 2],
}

const fn slot(role: &'static str, dx: i32, dy: i32) -> ViewSlot {
    ViewSlot {
        role,
        grid_offset: [dx, dy],
    }
}

impl RigKind {
    /// Every fixed layout (not [`RigKind::Adaptive`], whose views are planned).
    pub const ALL: [Self; 6] = [
        Self::FiveView,
        Self::ThreeView,
        Self::Stereo,
        Self::Grid3x3,
        Self::Line5,
        Self::GridCross,
    ];

    /// Views in capture order; the reference (`center`) comes first so that the neighbours are
    /// planned from where the reference camera actually was.
    pub fn capture_order(self) -> Vec<ViewSlot> {
        match self {
            Self::FiveView => vec![
                slot("center", 0, 0),
                slot("left", -1, 0),
                slot("right", 1, 0),
                slot("top", 0, -1),
                slot("bottom", 0, 1),
            ],
            Self::ThreeView => vec![slot("center", 0, 0), slot("left", -1, 0), slot("right", 1, 0)],
            Self::Stereo => vec![slot("center", 0, 0), slot("right", 1, 0)],
            Self::Grid3x3 => vec![
                slot("center", 0, 0),
                slot("top-left", -1, -1),
                slot("top", 0, -1),
                slot("top-right", 1, -1),
                slot("right", 1, 0),
                slot("bottom-right", 1, 1),
                slot("bottom", 0, 1),
                slot("bottom-left", -1, 1),
                slot("left", -1, 0),
            ],
            Self::Line5 => vec![
                slot("center", 0, 0),
                slot("left2", -2, 0),
                slot("left", -1, 0),
                slot("right", 1, 0),
                slot("right2", 2, 0),
            ],
            Self::GridCross => {
                let mut slots = Self::Grid3x3.capture_order();
                slots.extend([
                    slot("right2", 2, 0),
                    slot("bottom2", 0, 2),
                    slot("left2", -2, 0),
                    slot("top2", 0, -2),
                ]);
                slots
            }
            Self::Adaptive => vec![slot("center", 0, 0)],
        }
    }

    /// Views in the layout's documented file order (what `record import --views` lists):
    /// five-view: center, left, right, top, bottom; three-view: left, center, right; stereo:
    /// center, right; grid3x3 and grid-cross: row-major from the top; line5: left to right.
    pub fn file_order(self) -> Vec<ViewSlot> {
        match self {
            Self::ThreeView => vec![slot("left", -1, 0), slot("center", 0, 0), slot("right", 1, 0)],
            Self::Line5 => {
                let mut slots = self.capture_order();
                slots.sort_by_key(|s| s.grid_offset[0]);
                slots
            }
            Self::Grid3x3 | Self::GridCross => {
                let mut slots = self.capture_order();
                slots.sort_by_key(|s| (s.grid_offset[1], s.grid_offset[0]));
                slots
            }
            other => other.capture_order(),
        }
    }

    /// The name used on the command line and in the log.
    pub fn name(self) -> &'static str {
        match self {
            Self::FiveView => "five-view",
            Self::ThreeView => "three-view",
            Self::Stereo => "stereo",
            Self::Grid3x3 => "grid3x3",
            Self::Line5 => "line5",
            Self::GridCross => "grid-cross",
            Self::Adaptive => "adaptive",
        }
    }
}

/// The role name of a view at a grid offset (in baselines, x right, y down): `center`, `left`,
/// `right`, `top`, `bottom`, the diagonals `top-left` …, a multiple of one of these with the
/// multiple appended (`left2`, `right3`, `top-right2`), and `grid{x:+}{y:+}` (e.g. `grid+2-1`) for
/// any other offset. Roles name the topics (`/camera/<role>/…`) and `--neighbours`.
pub fn role_for_offset(offset: [i32; 2]) -> String {
    let [x, y] = offset;
    if x == 0 && y == 0 {
        return REFERENCE_ROLE.to_owned();
    }
    let multiple = if x == 0 || y == 0 || x.abs() == y.abs() {
        x.abs().max(y.abs())
    } else {
        return format!("grid{x:+}{y:+}");
    };
    let vertical = match y.signum() {
        -1 => "top",
        1 => "bottom",
        _ => "",
    };
    let horizontal = match x.signum() {
        -1 => "left",
        1 => "right",
        _ => "",
    };
    let direction = match (vertical.is_empty(), horizontal.is_empty()) {
        (true, _) => horizontal.to_owned(),
        (_, true) => vertical.to_owned(),
        _ => format!("{vertical}-{horizontal}"),
    };
    if multiple == 1 {
        direction
    } else {
        format!("{direction}{multiple}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_rig_has_one_reference_first_and_unique_roles() {
        for rig in RigKind::ALL {
            let order = rig.capture_order();
            assert_eq!(order[0].role, REFERENCE_ROLE);
            assert_eq!(order[0].grid_offset, [0, 0]);
            let mut roles: Vec<_> = order.iter().map(|s| s.role).collect();
            roles.sort_unstable();
            roles.dedup();
            assert_eq!(roles.len(), order.len());
            assert_eq!(rig.file_order().len(), order.len());
        }
        assert_eq!(RigKind::Grid3x3.file_order()[0].role, "top-left");
        assert_eq!(RigKind::ThreeView.file_order()[1].role, "center");
        assert_eq!(RigKind::GridCross.file_order()[0].role, "top2");
        assert_eq!(RigKind::GridCross.capture_order().len(), 13);
    }

    #[test]
    fn roles_follow_the_offsets() {
        for rig in RigKind::ALL {
            for slot in rig.capture_order() {
                assert_eq!(role_for_offset(slot.grid_offset), slot.role, "{slot:?}");
            }
        }
        assert_eq!(role_for_offset([-2, 0]), "left2");
        assert_eq!(role_for_offset([3, 0]), "right3");
        assert_eq!(role_for_offset([0, -2]), "top2");
        assert_eq!(role_for_offset([2, 2]), "bottom-right2");
        assert_eq!(role_for_offset([2, -1]), "grid+2-1");
    }
}

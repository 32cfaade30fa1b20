//! SemanticKITTI class ids the generator labels points with (low 16 bits of a `.label`).

/// No return, or the ego vehicle's own body.
pub const UNLABELED: u16 = 0;
/// A multipath echo measured below the ground.
pub const OUTLIER: u16 = 1;
/// Car.
pub const CAR: u16 = 10;
/// Person.
pub const PERSON: u16 = 30;
/// Road (also ramps and driving aisles).
pub const ROAD: u16 = 40;
/// Parking stalls.
pub const PARKING: u16 = 44;
/// Sidewalk.
pub const SIDEWALK: u16 = 48;
/// Other ground (a dirt track).
pub const OTHER_GROUND: u16 = 49;
/// Building.
pub const BUILDING: u16 = 50;
/// Fence and low walls.
pub const FENCE: u16 = 51;
/// Vegetation (bushes, tree crowns).
pub const VEGETATION: u16 = 70;
/// Tree trunk.
pub const TRUNK: u16 = 71;
/// Terrain (grass, soil).
pub const TERRAIN: u16 = 72;
/// Pole.
pub const POLE: u16 = 80;
/// Traffic sign.
pub const TRAFFIC_SIGN: u16 = 81;
/// Other object (boulders).
pub const OTHER_OBJECT: u16 = 99;

/// Whether a class is ground in SemanticKITTI's sense (as `config/labels/semantickitti.toml`).
pub fn is_ground(class: u16) -> bool {
    matches!(class, ROAD | PARKING | SIDEWALK | OTHER_GROUND | TERRAIN)
}

/// A plausible return intensity in [0, 1] for a surface of this class.
pub(crate) fn intensity(class: u16) -> f32 {
    match class {
        ROAD => 0.12,
        PARKING => 0.15,
        SIDEWALK => 0.25,
        OTHER_GROUND => 0.2,
        TERRAIN => 0.3,
        CAR => 0.45,
        PERSON => 0.3,
        POLE => 0.5,
        TRAFFIC_SIGN => 0.9,
        BUILDING => 0.35,
        FENCE => 0.3,
        VEGETATION => 0.4,
        TRUNK => 0.3,
        OTHER_OBJECT => 0.35,
        OUTLIER => 0.05,
        _ => 0.2,
    }
}

//! `groundwork sensors`: the presets as a table.

use std::process::ExitCode;

use anyhow::Result;
use groundwork_io::{SENSOR_PRESETS, sensor_preset};

/// `groundwork sensors`.
pub fn command() -> Result<ExitCode> {
    print!("{}", sensors_table()?);
    Ok(ExitCode::SUCCESS)
}

/// The presets as a table a person reads at a glance.
fn sensors_table() -> Result<String> {
    use std::fmt::Write;
    let mut s = format!(
        "{:<10} {:>7} {:>7} {:>7} {:>7} {:>6} {:>10} {:>9}  {}\n",
        "sensor", "height", "roll°", "pitch°", "yaw°", "ego m", "range m", "max pts", "about"
    );
    for (name, text) in SENSOR_PRESETS {
        let c = sensor_preset(name)?;
        let m = &c.sensor.mount;
        // The preset's first comment line says what the sensor is.
        let about = text
            .lines()
            .next()
            .and_then(|l| l.strip_prefix("# "))
            .unwrap_or("")
            .split(':')
            .next()
            .unwrap_or("");
        let _ = writeln!(
            s,
            "{:<10} {:>7.2} {:>7.1} {:>7.1} {:>7.1} {:>6.1} {:>10} {:>9}  {}",
            name,
            m.height,
            m.roll.to_degrees(),
            m.pitch.to_degrees(),
            m.yaw.to_degrees(),
            c.sensor.ego_radius,
            format!("{}–{}", c.zones.min_range, c.zones.max_range),
            c.sensor.max_points,
            about
        );
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_preset_is_a_row() {
        let table = sensors_table().unwrap();
        assert_eq!(table.lines().count(), SENSOR_PRESETS.len() + 1);
        assert!(table.contains("livox") && table.contains("1.10"), "{table}");
    }
}

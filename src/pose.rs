//! Pose truth per frame, pose files and the SPEC2021 / SPEED+ pose error.
//!
//! Convention (everywhere in faultcam: the ground-truth log, pose files, SUT output):
//! - Camera frame: x right, y down, z forward along the optical axis (metres).
//! - `t = [x, y, z]`: position of the target's body origin in the camera frame, metres.
//! - `q = [w, x, y, z]`: unit quaternion, **scalar first**, of the rotation **target body →
//!   camera**: a body point `p` is at `R(q) · p + t` in the camera frame. `q` and `-q` are the
//!   same attitude.
//! - Intrinsics `fx, fy, cx, cy` in pixels, OpenCV convention: the centre of the top-left pixel
//!   is (0, 0), so a camera point (X, Y, Z) images at `u = fx X/Z + cx`, `v = fy Y/Z + cy`.
//!
//! Errors (SPEC2021 / SPEED+ score): `E_t = ‖t_est − t‖ / ‖t‖` (relative, 1),
//! `E_q = 2 · arccos |⟨q_est, q⟩|` (radians, 0..=π, both quaternions normalised), score =
//! `E_t + E_q`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Pose of the target in the camera frame (see the module docs for the convention).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Rotation target → camera, scalar first `[w, x, y, z]`.
    pub q: [f64; 4],
    /// Target origin in the camera frame, metres.
    pub t: [f64; 3],
}

/// Pinhole intrinsics in pixels (OpenCV convention: top-left pixel centre at (0, 0)).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// What a source knows about a frame: the target pose and the camera.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Truth {
    pub pose: Option<Pose>,
    pub camera: Option<Intrinsics>,
}

impl Truth {
    pub fn is_empty(&self) -> bool {
        self.pose.is_none() && self.camera.is_none()
    }
}

/// Unit quaternion `[w, x, y, z]` of a rotation matrix (row-major, proper rotation), with
/// `w >= 0` (Shepperd's method: numerically stable for any angle).
pub fn quat_from_matrix(m: &[[f64; 3]; 3]) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    };
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let s = if q[0] < 0.0 { -1.0 / n } else { 1.0 / n };
    q.map(|v| v * s)
}

/// Rotation matrix (row-major) of a quaternion `[w, x, y, z]` (normalised first).
pub fn matrix_from_quat(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// `E_t = ‖t_est − t‖ / ‖t‖` (relative translation error, 1).
pub fn translation_error(est: &[f64; 3], truth: &[f64; 3]) -> f64 {
    let d = (0..3).map(|i| (est[i] - truth[i]).powi(2)).sum::<f64>().sqrt();
    let n = truth.iter().map(|v| v * v).sum::<f64>().sqrt();
    d / n
}

/// `E_q = 2 · arccos |⟨q_est, q⟩|` in radians (0..=π), both normalised.
pub fn rotation_error(est: &[f64; 4], truth: &[f64; 4]) -> f64 {
    let ne = est.iter().map(|v| v * v).sum::<f64>().sqrt();
    let nt = truth.iter().map(|v| v * v).sum::<f64>().sqrt();
    let d = (0..4).map(|i| est[i] * truth[i]).sum::<f64>().abs() / (ne * nt);
    2.0 * d.min(1.0).acos()
}

/// A pose a file or a SUT gave, checked: all values finite, `q` of non-zero norm (normalised
/// here).
pub fn check_pose(q: &[f64; 4], t: &[f64; 3]) -> Result<Pose, String> {
    if q.iter().chain(t.iter()).any(|v| !v.is_finite()) {
        return Err("a value is not a finite number".into());
    }
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n < 1e-9 {
        return Err("the quaternion has zero norm".into());
    }
    Ok(Pose { q: q.map(|v| v / n), t: *t })
}

/// One line of a pose file or of a SUT's output.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseLine {
    pub file: String,
    pub pose: Pose,
    pub camera: Option<Intrinsics>,
}

#[derive(Deserialize)]
struct JsonLine {
    file: String,
    q: [f64; 4],
    t: [f64; 3],
    #[serde(default)]
    camera: Option<Intrinsics>,
}

/// Parse one line of a pose file: JSON `{"file":"a.png","q":[w,x,y,z],"t":[x,y,z]}` (optional
/// `"camera":{"fx":..,"fy":..,"cx":..,"cy":..}`), or CSV `file,qw,qx,qy,qz,x,y,z` (SPEED+
/// order; commas or whitespace). `Ok(None)` for blank lines, `#` comments and a CSV header
/// (a line whose second field is not a number).
pub fn parse_pose_line(line: &str) -> Result<Option<PoseLine>, String> {
    let line = line.trim().trim_start_matches('\u{feff}');
    if line.is_empty() || line.starts_with('#') {
        return Ok(None);
    }
    if line.starts_with('{') {
        let j: JsonLine = serde_json::from_str(line).map_err(|e| format!("not a pose JSON object: {e}"))?;
        let pose = check_pose(&j.q, &j.t)?;
        return Ok(Some(PoseLine { file: base_name(&j.file), pose, camera: j.camera }));
    }
    let parts: Vec<&str> = line.split(|c: char| c == ',' || c.is_whitespace()).filter(|s| !s.is_empty()).collect();
    if parts.len() >= 2 && parts[1].parse::<f64>().is_err() && parts.len() == 8 {
        return Ok(None); // header
    }
    if parts.len() != 8 {
        return Err(format!(
            "expected 8 fields 'file,qw,qx,qy,qz,x,y,z' or a JSON object, got {} field(s)",
            parts.len()
        ));
    }
    let mut v = [0.0; 7];
    for (i, s) in parts[1..].iter().enumerate() {
        v[i] = s.parse().map_err(|_| format!("field {} '{s}' is not a number", i + 2))?;
    }
    let pose = check_pose(&[v[0], v[1], v[2], v[3]], &[v[4], v[5], v[6]])?;
    Ok(Some(PoseLine { file: base_name(parts[0]), pose, camera: None }))
}

/// File name without folders (poses join frames by file name).
pub fn base_name(s: &str) -> String {
    s.rsplit(['/', '\\']).next().unwrap_or(s).to_string()
}

/// A poses file (JSON Lines or SPEED+-style CSV) by file name. Errors name the file and line.
pub fn read_poses(path: &Path) -> Result<BTreeMap<String, PoseLine>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("poses file {}: {e}", path.display()))?;
    let mut map = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        match parse_pose_line(line) {
            Ok(Some(p)) => {
                if p.pose.t.iter().all(|v| *v == 0.0) {
                    return Err(format!("{}:{}: t is zero (E_t is relative to |t|)", path.display(), i + 1));
                }
                if map.insert(p.file.clone(), p).is_some() {
                    return Err(format!("{}:{}: a second pose for the same file", path.display(), i + 1));
                }
            }
            Ok(None) => {}
            Err(e) => return Err(format!("{}:{}: {e}", path.display(), i + 1)),
        }
    }
    if map.is_empty() {
        return Err(format!("poses file {} has no poses", path.display()));
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rot(axis: usize, deg: f64) -> [[f64; 3]; 3] {
        let (s, c) = deg.to_radians().sin_cos();
        let mut m = [[0.0; 3]; 3];
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        m[axis][axis] = 1.0;
        m[a][a] = c;
        m[a][b] = -s;
        m[b][a] = s;
        m[b][b] = c;
        m
    }

    #[test]
    fn quaternion_round_trips_and_angle_error_is_the_rotation_angle() {
        for (axis, deg) in [(0, 10.0), (1, 135.0), (2, 179.0), (0, -60.0), (1, 0.0)] {
            let m = rot(axis, deg);
            let q = quat_from_matrix(&m);
            let back = matrix_from_quat(q);
            for i in 0..3 {
                for j in 0..3 {
                    assert!((back[i][j] - m[i][j]).abs() < 1e-12, "{axis} {deg}");
                }
            }
            let id = [1.0, 0.0, 0.0, 0.0];
            let e = rotation_error(&q, &id);
            assert!((e - f64::to_radians(deg).abs()).abs() < 1e-9, "{deg}: {e}");
            // q and -q are the same attitude.
            assert!(rotation_error(&q.map(|v| -v), &q) < 1e-7);
        }
    }

    #[test]
    fn translation_error_is_relative() {
        assert!((translation_error(&[0.0, 0.0, 11.0], &[0.0, 0.0, 10.0]) - 0.1).abs() < 1e-12);
        assert_eq!(translation_error(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]), 0.0);
    }

    #[test]
    fn pose_lines_parse_json_and_csv_and_name_errors() {
        let j = parse_pose_line(r#"{"file":"img/a.png","q":[2,0,0,0],"t":[0,0,5]}"#).unwrap().unwrap();
        assert_eq!((j.file.as_str(), j.pose.q, j.pose.t), ("a.png", [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 5.0]));
        let c = parse_pose_line("b.jpg,1,0,0,0,0.1,0.2,7").unwrap().unwrap();
        assert_eq!((c.file.as_str(), c.pose.t), ("b.jpg", [0.1, 0.2, 7.0]));
        assert_eq!(parse_pose_line("filename,qw,qx,qy,qz,x,y,z").unwrap(), None);
        assert_eq!(parse_pose_line("  # comment").unwrap(), None);
        assert!(parse_pose_line("b.jpg,1,0,0").unwrap_err().contains("8 fields"));
        assert!(parse_pose_line("b.jpg,1,0,0,x,0,0,1").unwrap_err().contains("field 5 'x'"));
        assert!(parse_pose_line("b.jpg,0,0,0,0,0,0,1").unwrap_err().contains("zero norm"));
        assert!(parse_pose_line("{garbage").unwrap_err().contains("JSON"));
    }
}

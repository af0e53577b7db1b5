//! What `bridgev2w robot-info` tells about a robot: its actuated joints
//! (the column order of joint files) with limits and home pose, its links
//! and their label values, its end effectors (the order of actions), as
//! text or JSON.

use crate::embodiment::{builtin, Embodiment, BUILTIN_ROBOTS};
use crate::masks::label_of_link;
use std::fmt::Write as _;

/// The robot's flange link of `arm` when `name` is a built-in robot.
fn flange(name: &str, arm: &str) -> Option<&'static str> {
    builtin(name)
        .and_then(|s| s.arms.iter().find(|a| a.arm == arm))
        .map(|a| a.flange_link)
}

fn finite_or_null(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// The built-in robots, one line each (name, description, folder), as
/// `robot-info --list` prints them.
pub fn builtin_robots_text() -> String {
    let mut out = String::from("built-in robots (--robot NAME; or give a URDF file):\n");
    for b in BUILTIN_ROBOTS {
        let _ = writeln!(
            out,
            "  {:<15} {}{} (crates/embodiment/robots/{})",
            b.name,
            b.description,
            if b.synthetic_world {
                "; synth's tabletop world is laid out for it"
            } else {
                ""
            },
            b.folder
        );
    }
    out
}

/// The built-in robots as JSON: `[{name, description, folder, synthetic_world}]`.
pub fn builtin_robots_json() -> serde_json::Value {
    BUILTIN_ROBOTS
        .iter()
        .map(|b| {
            serde_json::json!({
                "name": b.name,
                "description": b.description,
                "description_folder": format!("crates/embodiment/robots/{}", b.folder),
                "synthetic_world": b.synthetic_world,
            })
        })
        .collect()
}

/// The description as JSON (`name`, `source`, `description`,
/// `description_folder`, `joints`, `links`, `end_effectors`, `action_dim`);
/// `name` is how the robot was named (a built-in name adds its description).
pub fn robot_info_json(e: &Embodiment, name: &str) -> serde_json::Value {
    let r = &e.robot;
    let spec = builtin(name);
    let limits = r.dof_limits();
    let joints: Vec<_> = r.dof_names().iter().zip(&limits).zip(&e.home).map(|((n, (lo, hi)), h)| {
        serde_json::json!({"name": n, "lower": finite_or_null(*lo), "upper": finite_or_null(*hi), "home": h})
    }).collect();
    let links: Vec<_> = r
        .links
        .iter()
        .enumerate()
        .map(|(i, l)| {
            serde_json::json!({
                "name": l.name,
                "label": l.mesh.as_ref().map(|_| label_of_link(i)),
                "triangles": l.mesh.as_ref().map_or(0, |m| m.triangles.len()),
                "closed": l.mesh_closed,
                "closed_triangles": l.mesh_closed_triangles,
            })
        })
        .collect();
    let end_effectors: Vec<_> = e.end_effectors.iter().map(|ee| serde_json::json!({
        "arm": ee.arm,
        "link": r.links[ee.link].name,
        "flange_link": flange(name, &ee.arm),
        "gripper_joint": ee.gripper_dof.map(|d| r.joints[r.dofs[d]].name.clone()),
        "gripper_closed_at": ee.gripper_dof.map(|_| format!("{:?}", ee.gripper_closed_at).to_lowercase()),
    })).collect();
    serde_json::json!({
        "name": r.name,
        "source": r.source_name,
        "description": spec.map(|s| s.description),
        "description_folder": spec.map(|s| format!("crates/embodiment/robots/{}", s.folder)),
        "joints": joints,
        "links": links,
        "end_effectors": end_effectors,
        "action_dim": e.action_dim(),
    })
}

/// The description as text, for a terminal.
pub fn robot_info_text(e: &Embodiment, name: &str) -> String {
    let r = &e.robot;
    let mut out = String::new();
    // Writing to a String cannot fail.
    let mut line = |s: String| {
        let _ = writeln!(out, "{s}");
    };
    line(format!("robot \"{}\" from {}", r.name, r.source_name));
    if let Some(s) = builtin(name) {
        line(format!("  {}", s.description));
        line(format!("  description folder: crates/embodiment/robots/{} (README: frames, joints, sources, licence)", s.folder));
    }
    line(format!(
        "\nactuated joints, in --joints column order ({}):",
        r.dof()
    ));
    for (i, (n, (lo, hi))) in r.dof_names().iter().zip(r.dof_limits()).enumerate() {
        line(format!(
            "  {i:>2}  {n:<28} [{lo:>9.4}, {hi:>9.4}]  home {:.4}",
            e.home[i]
        ));
    }
    line("\nlinks (label = value in labels.npy; 0 is background):".into());
    for (i, l) in r.links.iter().enumerate() {
        line(match &l.mesh {
            Some(m) => format!(
                "  {:>3}  {:<28} {} triangles",
                label_of_link(i),
                l.name,
                m.triangles.len()
            ),
            None => format!("    -  {:<28} (no geometry)", l.name),
        });
    }
    if e.end_effectors.is_empty() {
        line(
            "\nno end effectors: --actions needs --ee-link (joint trajectories work as is)".into(),
        );
        return out;
    }
    line(format!("\nend effectors, in --actions order ({}-D actions: [x,y,z,roll,pitch,yaw,gripper] per arm):", e.action_dim()));
    for ee in &e.end_effectors {
        let g = ee
            .gripper_dof
            .map_or("none".to_string(), |d| r.joints[r.dofs[d]].name.clone());
        let flange = flange(name, &ee.arm)
            .map(|f| format!(" (flange {f}: --ee-link {f} for recorded flange poses)"))
            .unwrap_or_default();
        line(format!(
            "  {:<6} link {:<24} gripper joint {g}{flange}",
            ee.arm, r.links[ee.link].name
        ));
    }
    out
}

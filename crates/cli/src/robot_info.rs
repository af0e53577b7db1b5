//! `bridgev2w robot-info`.

use crate::masks_cmd::RobotArgs;
use anyhow::Result;

macro_rules! outln {
    ($out:expr, $($arg:tt)*) => {{
        $out.push_str(&format!($($arg)*));
        $out.push('\n');
    }};
}
use bridgev2w_embodiment::masks::label_of_link;

/// Arguments of `robot-info`.
#[derive(Debug, clap::Args)]
pub struct RobotInfoArgs {
    #[command(flatten)]
    robot: RobotArgs,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(args: &RobotInfoArgs) -> Result<()> {
    let e = args.robot.load()?;
    let mut out = String::new();
    let r = &e.robot;
    let limits = r.dof_limits();
    let spec = bridgev2w_embodiment::embodiment::builtin(&args.robot.robot);
    let flange = |arm: &str| -> Option<&str> {
        spec.and_then(|s| s.arms.iter().find(|a| a.arm == arm))
            .map(|a| a.flange_link)
    };
    if args.json {
        let v = serde_json::json!({
            "name": r.name,
            "source": r.source_name,
            "description": spec.map(|s| s.description),
            "description_folder": spec.map(|s| format!("crates/embodiment/robots/{}", s.folder)),
            "joints": r.dof_names().iter().zip(&limits).zip(&e.home).map(|((n, (lo, hi)), h)| {
                serde_json::json!({"name": n, "lower": finite_or_null(*lo), "upper": finite_or_null(*hi), "home": h})
            }).collect::<Vec<_>>(),
            "links": r.links.iter().enumerate().map(|(i, l)| serde_json::json!({
                "name": l.name,
                "label": l.mesh.as_ref().map(|_| label_of_link(i)),
                "triangles": l.mesh.as_ref().map_or(0, |m| m.triangles.len()),
                "closed": l.mesh_closed,
                "closed_triangles": l.mesh_closed_triangles,
            })).collect::<Vec<_>>(),
            "end_effectors": e.end_effectors.iter().map(|ee| serde_json::json!({
                "arm": ee.arm,
                "link": r.links[ee.link].name,
                "flange_link": flange(&ee.arm),
                "gripper_joint": ee.gripper_dof.map(|d| r.joints[r.dofs[d]].name.clone()),
                "gripper_closed_at": ee.gripper_dof.map(|_| format!("{:?}", ee.gripper_closed_at).to_lowercase()),
            })).collect::<Vec<_>>(),
            "action_dim": e.action_dim(),
        });
        outln!(out, "{}", serde_json::to_string_pretty(&v)?);
        return crate::print_stdout(&out);
    }
    outln!(out, "robot \"{}\" from {}", r.name, r.source_name);
    if let Some(s) = spec {
        outln!(out, "  {}", s.description);
        outln!(
            out,
            "  description folder: crates/embodiment/robots/{} (README: frames, joints, sources, licence)",
            s.folder
        );
    }
    outln!(
        out,
        "\nactuated joints, in --joints column order ({}):",
        r.dof()
    );
    for (i, (name, (lo, hi))) in r.dof_names().iter().zip(&limits).enumerate() {
        outln!(
            out,
            "  {i:>2}  {name:<28} [{lo:>9.4}, {hi:>9.4}]  home {:.4}",
            e.home[i]
        );
    }
    outln!(
        out,
        "\nlinks (label = value in labels.npy; 0 is background):"
    );
    for (i, l) in r.links.iter().enumerate() {
        match &l.mesh {
            Some(m) => outln!(
                out,
                "  {:>3}  {:<28} {} triangles",
                label_of_link(i),
                l.name,
                m.triangles.len()
            ),
            None => outln!(out, "    -  {:<28} (no geometry)", l.name),
        }
    }
    if e.end_effectors.is_empty() {
        outln!(
            out,
            "\nno end effectors: --actions needs --ee-link (joint trajectories work as is)"
        );
    } else {
        outln!(out,
            "\nend effectors, in --actions order ({}-D actions: [x,y,z,roll,pitch,yaw,gripper] per arm):",
            e.action_dim()
        );
        for ee in &e.end_effectors {
            let g = ee
                .gripper_dof
                .map_or("none".to_string(), |d| r.joints[r.dofs[d]].name.clone());
            let flange = flange(&ee.arm)
                .map(|f| format!(" (flange {f}: --ee-link {f} for recorded flange poses)"))
                .unwrap_or_default();
            outln!(
                out,
                "  {:<6} link {:<24} gripper joint {g}{flange}",
                ee.arm,
                r.links[ee.link].name
            );
        }
    }
    crate::print_stdout(&out)
}

fn finite_or_null(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

//! `bridgev2w robot-info`.

use crate::masks_cmd::RobotArgs;
use anyhow::{bail, Result};

use bridgev2w_embodiment::robot_info::{
    builtin_robots_json, builtin_robots_text, robot_info_json, robot_info_text,
};

/// Arguments of `robot-info`.
#[derive(Debug, clap::Args)]
pub struct RobotInfoArgs {
    #[command(flatten)]
    robot: Option<RobotArgs>,
    /// List the built-in robots instead.
    #[arg(long, conflicts_with = "robot")]
    list: bool,
    /// Print JSON instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(args: &RobotInfoArgs) -> Result<()> {
    let robot = match (&args.robot, args.list) {
        (_, true) if args.json => {
            let v = builtin_robots_json();
            return crate::print_stdout(&format!("{}\n", serde_json::to_string_pretty(&v)?));
        }
        (_, true) => return crate::print_stdout(&builtin_robots_text()),
        (Some(r), false) => r,
        (None, false) => bail!("give --robot NAME (a built-in robot or a URDF file) or --list"),
    };
    let e = robot.load()?;
    let name = &robot.robot;
    if args.json {
        let v = robot_info_json(&e, name);
        return crate::print_stdout(&format!("{}\n", serde_json::to_string_pretty(&v)?));
    }
    crate::print_stdout(&robot_info_text(&e, name))
}

//! `bridgev2w robot-info`.

use crate::masks_cmd::RobotArgs;
use anyhow::Result;

use bridgev2w_embodiment::robot_info::{robot_info_json, robot_info_text};

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
    let name = &args.robot.robot;
    if args.json {
        let v = robot_info_json(&e, name);
        return crate::print_stdout(&format!("{}\n", serde_json::to_string_pretty(&v)?));
    }
    crate::print_stdout(&robot_info_text(&e, name))
}

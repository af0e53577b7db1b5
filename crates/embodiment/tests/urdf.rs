//! URDF parsing: joint types, mimic, geometry, mesh paths and bad input.

use bridgev2w_embodiment::robot::{mesh_candidates, JointKind, JointSource, LoadOptions, Robot};
use std::path::Path;

fn load(text: &str) -> Result<Robot, String> {
    Robot::from_urdf_str(text, "test.urdf", None, &LoadOptions::default())
        .map_err(|e| e.to_string())
}

const TREE: &str = r#"<?xml version="1.0"?>
<robot name="tree">
  <link name="base"><visual><geometry><box size="0.2 0.2 0.1"/></geometry></visual></link>
  <link name="a"><visual><origin xyz="0 0 0.1"/><geometry><cylinder radius="0.02" length="0.2"/></geometry></visual></link>
  <link name="b"><visual><geometry><sphere radius="0.03"/></geometry></visual>
                 <visual><geometry><capsule radius="0.01" length="0.05"/></geometry></visual></link>
  <link name="c"/>
  <link name="d"/>
  <joint name="j_slide" type="prismatic"><parent link="base"/><child link="a"/><axis xyz="0 0 2"/>
    <limit lower="0" upper="0.5" effort="1" velocity="1"/></joint>
  <joint name="j_spin" type="continuous"><parent link="a"/><child link="b"/><origin xyz="0 0 0.2" rpy="0 0 1.5707963267948966"/><axis xyz="1 0 0"/></joint>
  <joint name="j_fixed" type="fixed"><parent link="b"/><child link="c"/><origin xyz="0.1 0 0"/></joint>
  <joint name="j_mimic" type="revolute"><parent link="base"/><child link="d"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="j_spin" multiplier="-2" offset="0.1"/></joint>
</robot>"#;

#[test]
fn joint_types_mimic_and_geometry() {
    let r = load(TREE).expect("valid");
    assert_eq!(r.dof_names(), vec!["j_slide", "j_spin"]);
    assert_eq!(r.links[0].name, "base");
    let j = r.joint_index("j_mimic").expect("mimic");
    assert_eq!(
        r.joints[j].source,
        JointSource::Mimic {
            dof: 1,
            multiplier: -2.0,
            offset: 0.1
        }
    );
    assert_eq!(
        r.joints[r.joint_index("j_spin").expect("spin")].kind,
        JointKind::Continuous
    );
    assert_eq!(r.dof_limits()[1], (f64::NEG_INFINITY, f64::INFINITY));
    // Axis normalised: sliding 0.3 moves 0.3 m, not 0.6.
    let q = [0.3, 0.5];
    let poses = r.link_poses(&q);
    let (a, c, d) = (
        r.link_index("a").expect("a"),
        r.link_index("c").expect("c"),
        r.link_index("d").expect("d"),
    );
    assert!((poses[a].translation.z - 0.3).abs() < 1e-12);
    // c: base -> slide 0.3 -> up 0.2 -> yaw 90deg -> spin about x -> +0.1 in x (which is world y).
    let pc = poses[c].translation.vector;
    assert!(
        (pc - nalgebra::Vector3::new(0.0, 0.1, 0.5)).norm() < 1e-12,
        "{pc}"
    );
    // Mimic: angle = -2 * 0.5 + 0.1 = -0.9 about z.
    let angle =
        poses[d].rotation.angle() * poses[d].rotation.axis().map_or(1.0, |ax| ax.z.signum());
    assert!((angle + 0.9).abs() < 1e-12, "{angle}");
    // Geometry: visual origins are baked into the link mesh.
    let mesh_a = r.links[a].mesh.as_ref().expect("mesh");
    let (lo, hi) = mesh_a.bounds().expect("bounds");
    assert!(
        (lo.z - 0.0).abs() < 1e-6 && (hi.z - 0.2).abs() < 1e-6,
        "{lo} {hi}"
    );
    let mesh_b = r.links[r.link_index("b").expect("b")]
        .mesh
        .as_ref()
        .expect("mesh");
    let (lo, hi) = mesh_b.bounds().expect("bounds");
    assert!(
        (hi.z - 0.035).abs() < 1e-6 && (lo.x + 0.03).abs() < 1e-3,
        "sphere + capsule merged: {lo} {hi}"
    );
    assert!(r.links[c].mesh.is_none());
}

fn expect_err(text: &str, needles: &[&str]) {
    let err = load(text).expect_err("should fail");
    for n in needles {
        assert!(err.contains(n), "error {err:?} should mention {n:?}");
    }
    assert!(err.contains("test.urdf"), "error names the source: {err}");
}

#[test]
fn bad_urdf_gets_clear_errors() {
    expect_err("<robot name='x'><link name='a'>", &["malformed URDF"]);
    expect_err("not xml at all", &["malformed URDF"]);
    expect_err("<robot name='x'></robot>", &["no <link>"]);
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/></robot>",
        &["one root link", "a, b"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><joint name='j' type='fixed'><parent link='a'/><child link='zz'/></joint></robot>",
        &["joint \"j\"", "child link \"zz\""],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='floating'><parent link='a'/><child link='b'/></joint></robot>",
        &["joint \"j\"", "not supported"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent link='a'/><child link='b'/><axis xyz='0 0 0'/><limit lower='-1' upper='1' effort='1' velocity='1'/></joint></robot>",
        &["joint \"j\"", "axis"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent link='a'/><child link='b'/><limit lower='1' upper='-1' effort='1' velocity='1'/></joint></robot>",
        &["joint \"j\"", "lower=1 upper=-1"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'><parent link='a'/><child link='b'/><limit lower='-1' upper='1' effort='1' velocity='1'/><mimic joint='nope'/></joint></robot>",
        &["mimic", "nope"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='fixed'><origin xyz='0 NaN 0'/><parent link='a'/><child link='b'/></joint></robot>",
        &["joint \"j\"", "finite"],
    );
    expect_err(
        "<robot name='x'><link name='a'><visual><geometry><sphere radius='-1'/></geometry></visual></link></robot>",
        &["link \"a\"", "radius=-1"],
    );
    expect_err(
        "<robot name='x'><link name='a'/><link name='a'/></robot>",
        &["link \"a\" is defined twice"],
    );
    expect_err(
        "<robot name='x'><link name='a'><visual><geometry><mesh filename='package://pkg/meshes/gone.stl'/></geometry></visual></link></robot>",
        &["link \"a\"", "gone.stl", "not found", "--mesh-path"],
    );
}

#[test]
fn mesh_path_resolution() {
    let dir = tempfile::tempdir().expect("tmp");
    let pkg = dir.path().join("my_robot");
    std::fs::create_dir_all(pkg.join("urdf")).expect("mkdir");
    std::fs::create_dir_all(pkg.join("meshes")).expect("mkdir");
    let opts = LoadOptions {
        mesh_search_paths: vec![dir.path().to_path_buf()],
        ..Default::default()
    };
    let c = mesh_candidates(
        "package://my_robot/meshes/x.stl",
        Some(&pkg.join("urdf")),
        &opts,
    );
    assert!(c.contains(&pkg.join("meshes/x.stl")), "{c:?}");
    let c = mesh_candidates("meshes/x.stl", Some(Path::new("/a/b")), &opts);
    assert_eq!(c[0], Path::new("/a/b/meshes/x.stl"));
    assert!(c.contains(&dir.path().join("meshes/x.stl")));
    let c = mesh_candidates("file:///abs/x.stl", None, &opts);
    assert_eq!(c, vec![Path::new("/abs/x.stl").to_path_buf()]);
}

#[test]
fn unknown_mesh_format_names_the_file() {
    let dir = tempfile::tempdir().expect("tmp");
    std::fs::write(
        dir.path().join("part.ply"),
        b"ply\nformat ascii 1.0\nend_header\n",
    )
    .expect("write");
    let urdf = dir.path().join("r.urdf");
    std::fs::write(
        &urdf,
        "<robot name='x'><link name='a'><visual><geometry><mesh filename='part.ply'/></geometry></visual></link></robot>",
    )
    .expect("write");
    let err = Robot::from_urdf_file(&urdf, &LoadOptions::default())
        .expect_err("ply")
        .to_string();
    assert!(
        err.contains("part.ply") && err.contains("link \"a\""),
        "{err}"
    );
    assert!(
        err.contains(".stl") || err.contains("stl"),
        "lists supported formats: {err}"
    );
}

#[test]
fn package_meshes_are_found_scaled_and_welded() {
    use bridgev2w_embodiment::mesh::TriMesh;
    let dir = tempfile::tempdir().expect("tmp");
    let pkg = dir.path().join("ws/src/my_robot");
    std::fs::create_dir_all(pkg.join("meshes")).expect("mkdir");
    std::fs::create_dir_all(dir.path().join("elsewhere")).expect("mkdir");
    std::fs::write(
        pkg.join("meshes/cube.stl"),
        TriMesh::cuboid([1.0, 1.0, 1.0]).to_binary_stl(),
    )
    .expect("stl");
    let urdf = dir.path().join("elsewhere/robot.urdf");
    std::fs::write(
        &urdf,
        r#"<robot name="r">
          <link name="a"><visual><origin xyz="0 0 1"/><geometry><mesh filename="package://my_robot/meshes/cube.stl" scale="2 1 0.5"/></geometry></visual></link>
          <link name="b"><visual><geometry><mesh filename="package://my_robot/meshes/cube.stl"/></geometry></visual></link>
          <joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint>
        </robot>"#,
    )
    .expect("urdf");
    // Not found without the search path; the error lists where it looked.
    let err = Robot::from_urdf_file(&urdf, &LoadOptions::default())
        .expect_err("no path")
        .to_string();
    assert!(
        err.contains("cube.stl") && err.contains("--mesh-path"),
        "{err}"
    );
    let opts = LoadOptions {
        mesh_search_paths: vec![dir.path().join("ws/src")],
        ..Default::default()
    };
    let r = Robot::from_urdf_file(&urdf, &opts).expect("found");
    let a = r.links[0].mesh.as_ref().expect("a mesh");
    let (lo, hi) = a.bounds().expect("bounds");
    assert_eq!((lo.x, hi.x, lo.z, hi.z), (-1.0, 1.0, 0.75, 1.25));
    assert_eq!(
        a.vertices.len(),
        8,
        "STL corners welded back to the cube's 8 vertices"
    );
    assert!(r.links[0].mesh_closed && r.links[1].mesh_closed);
}

#[test]
fn a_revolute_joint_without_limit_is_named() {
    let text = r#"<?xml version="1.0"?>
<robot name="r">
  <link name="base"/><link name="arm"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
  </joint>
</robot>"#;
    let e = load(text).expect_err("refused");
    assert!(
        e.contains("shoulder") && e.contains("no <limit") && e.contains("continuous"),
        "{e}"
    );
    let with_limit = text.replace(
        "<axis xyz=\"0 0 1\"/>",
        "<axis xyz=\"0 0 1\"/><limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>",
    );
    let robot = load(&with_limit).expect("ok");
    assert_eq!(robot.dof_limits(), vec![(-1.0, 1.0)]);
}

#[test]
fn a_urdf_file_where_a_builtin_robot_is_required_says_so() {
    use bridgev2w_embodiment::embodiment::Embodiment;
    let dir = tempfile::tempdir().expect("ok");
    let path = dir.path().join("some.urdf");
    std::fs::write(&path, TREE).expect("ok");
    let e = Embodiment::builtin(path.to_str().expect("ok"))
        .expect_err("refused")
        .to_string();
    assert!(
        e.contains("only built-in robots") && e.contains("franka"),
        "{e}"
    );
    let e = Embodiment::builtin("nope")
        .expect_err("refused")
        .to_string();
    assert!(e.contains("no such URDF file"), "{e}");
}

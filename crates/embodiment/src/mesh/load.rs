//! Mesh files: STL, OBJ, COLLADA (via mesh-loader) and glTF/GLB (via gltf).

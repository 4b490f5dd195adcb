// splatdeform editor page: deformed points / surfels and mesh vertices (the host prepends
// "#define K k", deform.glsl and shading.glsl).
in vec3 position;
in vec3 normal;
in vec4 color;
in float label;
uniform mat4 modelViewMatrix;
uniform mat4 projectionMatrix;
uniform mat3 normalMatrix;
uniform float u_size;      // point diameter, model units
uniform float u_px;        // pixels per unit at distance 1 (viewport height / 2 * P[1][1])
uniform float u_has_normals;
out vec3 v_color;
out vec3 v_view_pos;

void main() {
    vec3 p = position;
    mat3 J = deform_point(gl_VertexID, p);
    vec4 view_pos = modelViewMatrix * vec4(p, 1.0);
    v_view_pos = view_pos.xyz;
    vec3 c = region_tint(color.rgb, label);
    if (u_has_normals > 0.5) {
        c = lit(c, normalize(normalMatrix * deform_normal(J, normal)));
    }
    v_color = c;
    gl_Position = projectionMatrix * view_pos;
    gl_PointSize = clamp(u_size * u_px / max(-view_pos.z, 1e-6), 1.0, 64.0);
}

// splatdeform: shade mesh triangles by the interpolated deformed vertex normal.
// The host prepends "#version 330 core" and shading.glsl.

in vec3 v_normal;
in vec3 v_view_pos;
in vec3 v_color;

uniform mat4 u_view;

out vec4 f_color;

void main() {
    vec3 normal = mat3(u_view) * v_normal;
    f_color = vec4(headlight(v_color, normal, v_view_pos), 1.0);
}

// splatdeform: the deforming vertex stage of surfels, point splats and meshes.
//
// Per point (vertex attributes): in_position (vec3), in_normal (vec3), in_axis_u / in_axis_v
// (vec3 tangent axes), in_color; the basis as in deform.glsl (pasted before this file).
//
// Math (identical to splatdeform/frame.py):
//   p' = p + sum_k b_k delta_k
//   J  = I + sum_k outer(delta_k, grad b_k)
//   n' = normalize(cof(J) n),  cof(J) n = n.x (c1 x c2) + n.y (c2 x c0) + n.z (c0 x c1)
//   u' = J u,  v' = J v
//
// The host prepends "#version 330 core" (or "#version 430 core" when K > 4), "#define DEFORM 0|1",
// with DEFORM 1 "#define K <k>" (4 for the attribute path), then deform.glsl.

in vec3 in_position;
in vec3 in_normal;
in vec3 in_axis_u;
in vec3 in_axis_v;
in vec3 in_color;

uniform mat4 u_view;
uniform mat4 u_proj;

out vec3 v_position;   // deformed position (model units, relative to the upload origin)
out vec3 v_normal;     // deformed unit normal (zero when the input normal is zero)
out vec3 v_axis_u;     // deformed tangent axes
out vec3 v_axis_v;
out vec3 v_color;
out vec3 v_view_pos;   // view-space position (mesh shading)

void main() {
    vec3 p = in_position;
    vec3 n = in_normal;
    vec3 u = in_axis_u;
    vec3 v = in_axis_v;
#if DEFORM
    mat3 J = deform_point(p);
    u = J * u;
    v = J * v;
    vec3 cn = n.x * cross(J[1], J[2]) + n.y * cross(J[2], J[0]) + n.z * cross(J[0], J[1]);
    float len = length(cn);
    n = len > 0.0 ? cn / len : vec3(0.0);
#endif
    v_position = p;
    v_normal = n;
    v_axis_u = u;
    v_axis_v = v;
    v_color = in_color;
    vec4 view_pos = u_view * vec4(p, 1.0);
    v_view_pos = view_pos.xyz;
    gl_Position = u_proj * view_pos;
}

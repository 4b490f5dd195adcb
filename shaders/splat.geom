// splatdeform: expand each (deformed) splat into a quad spanned by its tangent axes.
// Corners c +- u +- v; g_local in [-1, 1]^2 lets the fragment stage cut the ellipse
// (s u + t v with s^2 + t^2 <= 1). Splats with zero axes are dropped.
// u_depth_offset > 0 (the depth pre-pass of surface splatting) pushes the quad back along the
// view ray by that many splat radii (the longer axis), so splats of one surface within that
// distance behind the front-most one still pass the depth test and blend.
// The host prepends "#version 330 core".

layout(points) in;
layout(triangle_strip, max_vertices = 4) out;

in vec3 v_position[];
in vec3 v_normal[];
in vec3 v_axis_u[];
in vec3 v_axis_v[];
in vec3 v_color[];

uniform mat4 u_view;
uniform mat4 u_proj;
uniform float u_depth_offset;
uniform float u_splat_scale;   // axes scaled by this (surface splatting: > 1, overlap)

out vec2 g_local;
out vec3 g_normal;     // view space
out vec3 g_view_pos;
out vec3 g_color;

void main() {
    vec3 u = v_axis_u[0] * u_splat_scale;
    vec3 v = v_axis_v[0] * u_splat_scale;
    if (dot(u, u) == 0.0 || dot(v, v) == 0.0) {
        return;
    }
    vec3 normal = mat3(u_view) * v_normal[0];
    float push = u_depth_offset * sqrt(max(dot(u, u), dot(v, v)));
    const vec2 corners[4] = vec2[4](vec2(-1.0, -1.0), vec2(1.0, -1.0),
                                    vec2(-1.0, 1.0), vec2(1.0, 1.0));
    for (int i = 0; i < 4; ++i) {
        vec3 world = v_position[0] + corners[i].x * u + corners[i].y * v;
        vec4 view_pos = u_view * vec4(world, 1.0);
        view_pos.xyz += push * normalize(view_pos.xyz);
        g_local = corners[i];
        g_normal = normal;
        g_view_pos = view_pos.xyz;
        g_color = v_color[0];
        gl_Position = u_proj * view_pos;
        EmitVertex();
    }
    EndPrimitive();
}

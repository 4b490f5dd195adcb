// splatdeform: one screen-aligned quad per Gaussian covering its 3-sigma box (window pixels).
// Culled splats (opacity 0) emit nothing. Depth is not used: splats are drawn sorted back to
// front and blended. The host prepends "#version 330 core".

layout(points) in;
layout(triangle_strip, max_vertices = 4) out;

in vec4 v_color[];
in vec3 v_conic[];
in vec2 v_center[];
in vec2 v_extent[];

uniform vec2 u_viewport;

flat out vec4 g_color;
flat out vec3 g_conic;
flat out vec2 g_center;

void main() {
    if (v_color[0].a <= 0.0) {
        return;
    }
    const vec2 corners[4] = vec2[4](vec2(-1.0, -1.0), vec2(1.0, -1.0),
                                    vec2(-1.0, 1.0), vec2(1.0, 1.0));
    for (int i = 0; i < 4; ++i) {
        vec2 window = v_center[0] + corners[i] * v_extent[0];
        g_color = v_color[0];
        g_conic = v_conic[0];
        g_center = v_center[0];
        gl_Position = vec4(window / u_viewport * 2.0 - 1.0, 0.0, 1.0);
        EmitVertex();
    }
    EndPrimitive();
}

// splatdeform: cut the splat quad to its ellipse and shade it by the deformed normal.
// The host prepends "#version 330 core" and shading.glsl.

in vec2 g_local;
in vec3 g_normal;
in vec3 g_view_pos;
in vec3 g_color;

out vec4 f_color;

void main() {
    if (dot(g_local, g_local) > 1.0) {
        discard;
    }
    f_color = vec4(headlight(g_color, g_normal, g_view_pos), 1.0);
}

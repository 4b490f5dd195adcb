// splatdeform: surface splatting pass 1, depth only: the (offset) elliptical disc.
// The host prepends "#version 330 core".

in vec2 g_local;

void main() {
    if (dot(g_local, g_local) > 1.0) {
        discard;
    }
}

// splatdeform: one triangle covering the viewport (surface splatting pass 3).
// The host prepends "#version 330 core".

void main() {
    vec2 corner = vec2(float((gl_VertexID & 1) * 4 - 1), float((gl_VertexID & 2) * 2 - 1));
    gl_Position = vec4(corner, 0.0, 1.0);
}

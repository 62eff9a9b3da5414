// Streams the index-finger pad pose to `tactdeform-hw render --tracking udp://HOST:PORT`, one UDP datagram
// per frame: "t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz" (UTF-8, invariant culture).
//
// Unity's world is left-handed, Y up, metres; the package's is right-handed, Z up, millimetres. Swapping
// Y and Z (a mirror: handedness flips) and multiplying by 1000 turns one into the other. The pad frame is
// built from two directions of the fingertip (toward the tip, out of the pad), each swapped the same way;
// its right is Vector3.Cross(padNormal, tipDirection) in Unity's numbers (a mirror reverses the cross
// product), and the quaternion is taken from those three axes on the package's side of the mirror.
// tactdeform_hw/render/unity.py is the same conversion in Python, and tests/test_live_unity.py checks it
// against poses whose answer is known.
//
// Attach to any GameObject; set `fingertip` to the index-finger tip bone (OVRSkeleton's Hand_IndexTip, or
// a child placed on the pad) and `sceneOrigin` to where the scene's origin sits in the virtual world.
// Choose which local axes of the tip transform point toward the tip and out of the pad for your rig.

using System;
using System.Globalization;
using System.Net.Sockets;
using System.Text;
using UnityEngine;

public class TactDeformSender : MonoBehaviour
{
    public string host = "127.0.0.1";
    public int port = 9870;
    public Transform fingertip;
    public Transform sceneOrigin;                      // null: Unity's world origin
    public Vector3 localTipAxis = Vector3.forward;     // the tip bone's local axis toward the fingertip
    public Vector3 localPadNormal = Vector3.down;      // its local axis out of the pad
    public bool sendHeader = false;                    // prefix every datagram with the CSV header line

    const string Header = "t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz\n";
    UdpClient client;

    void OnEnable() { client = new UdpClient(); client.Connect(host, port); }
    void OnDisable() { client?.Close(); client = null; }

    // Hand tracking updates at the display rate (72 Hz on Quest 3); one sample per rendered frame.
    void Update()
    {
        if (client == null || fingertip == null) return;
        Vector3 anchor = sceneOrigin != null ? sceneOrigin.position : Vector3.zero;
        Vector3 p = (fingertip.position - anchor) * 1000f;                      // metres -> millimetres
        Vector3 tip = fingertip.TransformDirection(localTipAxis).normalized;
        Vector3 normal = fingertip.TransformDirection(localPadNormal);
        normal = (normal - Vector3.Dot(normal, tip) * tip).normalized;         // perpendicular to the tip
        Vector3 right = Vector3.Cross(normal, tip);                             // the pad's right, mirrored
        // Unity (x, y, z) -> package (x, z, y)
        double[] x = { right.x, right.z, right.y };
        double[] y = { tip.x, tip.z, tip.y };
        double[] z = { normal.x, normal.z, normal.y };
        double[] q = QuaternionOfAxes(x, y, z);
        string line = string.Join(",",
            ((double)Time.realtimeSinceStartupAsDouble).ToString("R", CultureInfo.InvariantCulture),
            ((double)p.x).ToString("R", CultureInfo.InvariantCulture),
            ((double)p.z).ToString("R", CultureInfo.InvariantCulture),
            ((double)p.y).ToString("R", CultureInfo.InvariantCulture),
            q[0].ToString("R", CultureInfo.InvariantCulture),
            q[1].ToString("R", CultureInfo.InvariantCulture),
            q[2].ToString("R", CultureInfo.InvariantCulture),
            q[3].ToString("R", CultureInfo.InvariantCulture));
        byte[] bytes = Encoding.UTF8.GetBytes(sendHeader ? Header + line : line);
        try { client.Send(bytes, bytes.Length); } catch (SocketException) { /* receiver not up yet */ }
    }

    // (w, x, y, z) with w >= 0 of the rotation whose columns are x, y, z (Shepperd's method, as the package's
    // matrix_to_quat).
    static double[] QuaternionOfAxes(double[] x, double[] y, double[] z)
    {
        double m00 = x[0], m10 = x[1], m20 = x[2];
        double m01 = y[0], m11 = y[1], m21 = y[2];
        double m02 = z[0], m12 = z[1], m22 = z[2];
        double tr = m00 + m11 + m22, s;
        double[] q;
        if (tr > 0) {
            s = Math.Sqrt(tr + 1.0) * 2;
            q = new[] { 0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s };
        } else if (m00 > m11 && m00 > m22) {
            s = Math.Sqrt(1.0 + m00 - m11 - m22) * 2;
            q = new[] { (m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s };
        } else if (m11 > m22) {
            s = Math.Sqrt(1.0 + m11 - m00 - m22) * 2;
            q = new[] { (m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s };
        } else {
            s = Math.Sqrt(1.0 + m22 - m00 - m11) * 2;
            q = new[] { (m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s };
        }
        double n = Math.Sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        double sign = q[0] < 0 ? -1.0 : 1.0;
        for (int i = 0; i < 4; i++) q[i] = sign * q[i] / n;
        return q;
    }
}
